"""The app configuration file turned into environment variables: read, checked, translated.

Pure Python (standard library, no Django), so every container can run it before anything
starts, and the HEALTHCHECK can read the gateway's Redis URL the same way (through config.py).
config.py (the script entrypoint.sh runs) has the file's format and applies the result:
`env` prints these variables as shell exports; `setup` registers robots_wanted() in the database.

Each part of the file is optional and an empty value sets nothing; a value that cannot be right
raises ConfigError with what to fix (config.py logs it and exits with 78).
"""
from __future__ import annotations

import json
import os
import re
from pathlib import Path
from urllib.parse import parse_qsl, quote, unquote, urlencode, urlsplit, urlunsplit

CONFIG_FILE = Path(os.environ.get("LIFECYCLE_CONFIG_FILE", "/cfg-data/param.json"))
DISCOVERY_RANGES = ("SUBNET", "LOCALHOST", "OFF", "SYSTEM_DEFAULT")
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")
# As the site names gateways (ros_gateway/shared/protocol.py) and their Redis users (gw-NAME).
GATEWAY_NAME = re.compile(r"[a-z0-9][a-z0-9_-]{0,62}")
CHANNEL_PREFIX = re.compile(r"[A-Za-z0-9_.-]{1,64}")
# A DDS peer (ROS_STATIC_PEERS): a host name, an IPv4 or IPv6 address.
DDS_PEER = re.compile(r"[A-Za-z0-9][A-Za-z0-9.:-]*|\[[0-9A-Fa-f:.]+\]")
# The CA certificate of a rediss:// URL (redis.caCertificate) is written here for redis-py.
REDIS_CA_FILE = Path(os.environ.get("LIFECYCLE_REDIS_CA_FILE", "/tmp/lifecycle-redis-ca.crt"))
# The languages of e-mails, webhooks, the CLI and the pages' fallback (LIFECYCLE_LANGUAGE).
LANGUAGES = ("en", "de")
class ConfigError(Exception):
    """A value of the configuration that cannot work; the message says which and what to write."""


def read_config() -> dict:
    """The configuration file as a dict ({} when there is none), the types of its parts checked."""
    if not CONFIG_FILE.is_file():
        return {}
    try:
        data = json.loads(CONFIG_FILE.read_text(encoding="utf-8") or "{}")
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{CONFIG_FILE} is not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{CONFIG_FILE} must hold a JSON object")
    for part in ("admin", "site", "ros", "gateway", "redis", "signIn"):
        if not isinstance(data.get(part, {}), dict):
            raise ConfigError(f"{CONFIG_FILE}: '{part}' must be an object")
    for part in ("oidc", "ldap"):
        if not isinstance(data.get("signIn", {}).get(part, {}), dict):
            raise ConfigError(f"{CONFIG_FILE}: 'signIn.{part}' must be an object")
    if not isinstance(data.get("robots", []), list):
        raise ConfigError(f"{CONFIG_FILE}: 'robots' must be a list")
    return data


def _text(value) -> str:
    if isinstance(value, list):
        return ",".join(str(v).strip() for v in value if str(v).strip())
    return "" if value is None else str(value).strip()


def _comma_list(value) -> str:
    items = value if isinstance(value, list) else _text(value).split(",")
    return ",".join(str(item).strip() for item in items if str(item).strip())


def settings_env(config: dict) -> dict[str, str]:
    """The environment variables the configuration sets (only those with a value); the sign-in
    part's are sign_in_env.py's."""
    site, ros = config.get("site", {}), config.get("ros", {})
    env: dict[str, str] = {}

    def put(name: str, value) -> None:
        text = _text(value)
        if text:
            env[name] = text

    put("DJANGO_ALLOWED_HOSTS", _comma_list(site.get("allowedHosts")))
    put("DJANGO_CSRF_TRUSTED_ORIGINS", _comma_list(site.get("csrfTrustedOrigins")))
    prefix = _text(site.get("urlPrefix"))
    if prefix:
        if not re.fullmatch(r"(/[A-Za-z0-9._~-]+)+/?", prefix):
            raise ConfigError(f"site.urlPrefix {prefix!r} must look like /lifecycle")
        env["LIFECYCLE_URL_PREFIX"] = prefix.rstrip("/")
    if isinstance(site.get("behindTlsProxy"), bool):
        env["LIFECYCLE_BEHIND_TLS_PROXY"] = "1" if site["behindTlsProxy"] else "0"
    env.update(_log_env(site, "site"))
    language = _text(site.get("language")).lower()
    if language:
        if language not in LANGUAGES:
            raise ConfigError(f"site.language {language!r} must be one of {', '.join(LANGUAGES)} "
                              "(English, German)")
        env["LIFECYCLE_LANGUAGE"] = language
    scope = _text(ros.get("discoveryRange")).upper()
    if scope:
        if scope not in DISCOVERY_RANGES:
            raise ConfigError(f"ros.discoveryRange must be one of {', '.join(DISCOVERY_RANGES)}")
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = scope
    peers = ros.get("staticPeers")
    if isinstance(peers, list):
        peers = ";".join(str(p).strip() for p in peers if str(p).strip())
    peers = ";".join(p.strip() for p in _text(peers).replace(",", ";").split(";") if p.strip())
    for peer in filter(None, peers.split(";")):
        if not DDS_PEER.fullmatch(peer):
            raise ConfigError(f"ros.staticPeers: {peer!r} is not a host name or address (separate peers with ';')")
    put("ROS_STATIC_PEERS", peers)
    servers = ros.get("discoveryServer")
    if isinstance(servers, list):
        servers = ";".join(str(p).strip() for p in servers)
    # Fast DDS: ';' separates servers and an entry's position is its server id (empty ones allowed).
    servers = ";".join(part.strip() for part in _text(servers).split(";"))
    if servers.strip(";"):
        for server in filter(None, servers.split(";")):
            if not _server_address(server):
                raise ConfigError(f"ros.discoveryServer: {server!r} is not ADDRESS[:PORT] (e.g. 10.1.2.3:11811; "
                                  "separate servers with ';')")
        env["ROS_DISCOVERY_SERVER"] = servers
        super_client = ros.get("superClient", True)
        if not isinstance(super_client, bool):
            raise ConfigError("ros.superClient must be true or false")
        # A super client learns every participant from the server, as the gateway must to list
        # all nodes; a plain client only those it has matching endpoints with.
        env["ROS_SUPER_CLIENT"] = "TRUE" if super_client else "FALSE"
    timeout = ros.get("serviceTimeout")
    if timeout not in (None, ""):
        try:
            if float(timeout) <= 0:
                raise ValueError
        except (TypeError, ValueError):
            raise ConfigError("ros.serviceTimeout must be a positive number of seconds") from None
        env["LIFECYCLE_SERVICE_TIMEOUT"] = str(float(timeout))
    return env


def _check_pem(certificate: str, where: str) -> None:
    if "-----BEGIN CERTIFICATE-----" not in certificate or "-----END CERTIFICATE-----" not in certificate:
        raise ConfigError(f"{where} must be a PEM certificate (-----BEGIN CERTIFICATE----- ...)")


def _log_env(part: dict, where: str) -> dict[str, str]:
    """timeZone and logLevel of a part of the configuration."""
    env = {"TZ": _text(part.get("timeZone"))} if _text(part.get("timeZone")) else {}
    level = _text(part.get("logLevel")).upper()
    if level:
        if level not in LOG_LEVELS:
            raise ConfigError(f"{where}.logLevel must be one of {', '.join(LOG_LEVELS)}")
        env["LIFECYCLE_LOG_LEVEL"] = level
    return env


def _server_address(text: str) -> bool:
    """HOST[:PORT] of a Fast DDS discovery server (an IPv6 address in brackets)."""
    match = re.fullmatch(r"(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9][A-Za-z0-9.-]*)(?::(\d{1,5}))?", text)
    return bool(match) and (match.group(2) is None or 0 < int(match.group(2)) < 65536)


def _matching(gateway: dict, key: str, pattern: re.Pattern, what: str) -> str:
    """The gateway part's ``key`` ("" when not set); it must match ``pattern`` (``what`` says how)."""
    value = _text(gateway.get(key))
    if value and not pattern.fullmatch(value):
        raise ConfigError(f"gateway.{key} {value!r}: {what}")
    return value


def gateway_env(config: dict, write_files: bool = False) -> dict[str, str]:
    """The gateway's own settings (parts "gateway" and "redis"): its name, the site's Redis
    URL with the gateway's credentials, the key prefix. Only the gateway role reads them, so a
    site's web and ingest never follow a Redis URL meant for its gateway. With ``write_files``
    the CA certificate of a rediss:// URL is written to REDIS_CA_FILE."""
    gateway, redis = config.get("gateway", {}), config.get("redis", {})
    env = _log_env(gateway, "gateway")
    name = _matching(gateway, "name", GATEWAY_NAME, "lower-case letters, digits, '-' and '_' (e.g. cell-a), "
                     "as registered on the site with manage.py add_gateway")
    if name:
        env["LIFECYCLE_GATEWAY_NAME"] = name
    prefix = _matching(gateway, "channelPrefix", CHANNEL_PREFIX, "letters, digits, '.', '_' and '-' "
                       "(the site's LIFECYCLE_CHANNEL_PREFIX, usually lifecycle)")
    if prefix:
        env["LIFECYCLE_CHANNEL_PREFIX"] = prefix
    url = _text(redis.get("url"))
    username = _text(redis.get("username"))
    password = redis.get("password")
    password = "" if password is None else str(password).strip()
    certificate = _text(redis.get("caCertificate"))
    if not url:
        if username or password or certificate:
            raise ConfigError("redis.url is missing: the site's Redis, e.g. redis://site.plant.local:6379/0 "
                              "(or the whole REDIS_URL that manage.py add_gateway printed)")
        return env
    if not name:
        raise ConfigError("gateway.name is missing: the name the gateway was registered with on the site "
                          "(manage.py add_gateway NAME)")
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as exc:
        raise ConfigError(f"redis.url is not a Redis URL ({exc})") from None
    if parts.scheme not in ("redis", "rediss") or not parts.hostname:
        raise ConfigError("redis.url must look like redis://HOST:6379/0 or rediss://HOST:6380/0 (TLS)")
    if parts.path not in ("", "/") and not re.fullmatch(r"/\d{1,2}", parts.path):
        raise ConfigError(f"redis.url: {parts.path!r} is not a database number such as /0")
    user = username or unquote(parts.username or "")
    secret = password or unquote(parts.password or "")
    if user.startswith("gw-") and user != f"gw-{name}":
        raise ConfigError(f"the Redis user {user!r} belongs to the gateway {user[3:]!r}, not to gateway.name "
                          f"{name!r}: take both from the same add_gateway run")
    if not secret:
        raise ConfigError(f"redis: no password for the gateway {name!r}; it is in the REDIS_URL that "
                          "manage.py add_gateway printed on the site (or give redis.username and redis.password)")
    host = f"[{parts.hostname}]" if ":" in parts.hostname else parts.hostname
    netloc = f"{quote(user, safe='')}:{quote(secret, safe='')}@{host}" + (f":{port}" if port else "")
    query = parse_qsl(parts.query, keep_blank_values=True)
    if certificate:
        if parts.scheme != "rediss":
            raise ConfigError("redis.caCertificate is for TLS: the URL must start with rediss://")
        _check_pem(certificate, "redis.caCertificate")
        if write_files:
            REDIS_CA_FILE.parent.mkdir(parents=True, exist_ok=True)
            REDIS_CA_FILE.write_text(certificate.strip() + "\n")
        query = [(k, v) for k, v in query if k != "ssl_ca_certs"] + [("ssl_ca_certs", str(REDIS_CA_FILE))]
    env["REDIS_URL"] = urlunsplit(parts._replace(netloc=netloc, query=urlencode(query, safe="/")))
    return env


def robots_wanted(config: dict) -> list[dict]:
    """Robots from the configuration file plus LIFECYCLE_ROBOTS ("agv-1:21[:/ns],agv-2:22")."""
    robots = []
    for index, item in enumerate(config.get("robots", [])):
        if not isinstance(item, dict) or not _text(item.get("name")) or item.get("domainId") in (None, ""):
            raise ConfigError(f"robots[{index}] needs a name and a domainId")
        try:
            domain = int(item["domainId"])
        except (TypeError, ValueError):
            raise ConfigError(f"robots[{index}].domainId must be a number 0-232") from None
        robots.append(
            {
                "name": _text(item["name"]),
                "domain": domain,
                "namespace": _text(item.get("namespace")),
                "description": _text(item.get("description")),
                "enabled": item.get("enabled", True) is not False,
            }
        )
    for spec in filter(None, (s.strip() for s in os.environ.get("LIFECYCLE_ROBOTS", "").split(","))):
        parts = spec.split(":")
        if len(parts) not in (2, 3) or not parts[1].strip().isdigit():
            raise ConfigError(f"LIFECYCLE_ROBOTS entry {spec!r} must be NAME:DOMAIN or NAME:DOMAIN:/NAMESPACE")
        robots.append(
            {
                "name": parts[0].strip(),
                "domain": int(parts[1]),
                "namespace": parts[2].strip() if len(parts) == 3 else "",
                "description": "",
                "enabled": True,
            }
        )
    return robots
