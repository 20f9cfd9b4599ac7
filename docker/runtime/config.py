"""Apply the app configuration at container start (called by entrypoint.sh).

The configuration file ($LIFECYCLE_CONFIG_FILE, default /cfg-data/param.json) is what the
Industrial Edge Management writes from the JSON-Forms template (docker/edge/cfg-data-template):

    {
      "admin":  {"username": "admin", "password": "...", "email": ""},
      "site":   {"allowedHosts": "ied-1.plant.local", "csrfTrustedOrigins": "", "urlPrefix": "/lifecycle",
                 "behindTlsProxy": true, "timeZone": "Europe/Berlin", "logLevel": "INFO"},
      "ros":    {"discoveryRange": "SUBNET", "staticPeers": "", "discoveryServer": "", "superClient": true,
                 "serviceTimeout": 5},
      "robots": [{"name": "agv-1", "domainId": 21, "namespace": "", "description": "", "enabled": true}]
    }

A gateway of its own (docker/edge-cell: no site, it dials out to the central site's Redis)
takes its name and Redis from two more parts, which only the gateway role reads:

      "gateway": {"name": "cell-a", "channelPrefix": "lifecycle", "timeZone": "UTC", "logLevel": "INFO"},
      "redis":   {"url": "redis://site.plant.local:6379/0", "username": "gw-cell-a", "password": "...",
                  "caCertificate": "-----BEGIN CERTIFICATE-----..."}

`redis.url` may instead be the whole REDIS_URL that `manage.py add_gateway` printed (with the
gateway's user and password in it); `username`/`password`, when given, replace what the URL holds.

Every part is optional; an empty value leaves the environment's value in force.

    config.py env [ROLE]           print `export NAME='value'` lines for the settings (no Django);
                                   ROLE gateway also gets its name and Redis URL (gateway, redis)
    config.py setup                migrate, create/update the admin account, register the robots
                                   (all of the gateway "local", the one the site's compose runs)
    config.py wait-for-schema N    wait up to N seconds until the web container has migrated (ingest)
"""
from __future__ import annotations

import json
import os
import re
import secrets
import shlex
import sys
import time
from pathlib import Path
from urllib.parse import parse_qsl, quote, unquote, urlencode, urlsplit, urlunsplit

CONFIG_FILE = Path(os.environ.get("LIFECYCLE_CONFIG_FILE", "/cfg-data/param.json"))
DISCOVERY_RANGES = ("SUBNET", "LOCALHOST", "OFF", "SYSTEM_DEFAULT")
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")
# The gateway the site's own compose file runs; robots of other gateways (cells) are added with
# `manage.py add_robot NAME --domain N --gateway CELL` or in the admin.
LOCAL_GATEWAY = "local"
# As the site names gateways (ros_gateway/shared/protocol.py) and their Redis users (gw-NAME).
GATEWAY_NAME = re.compile(r"[a-z0-9][a-z0-9_-]{0,62}")
CHANNEL_PREFIX = re.compile(r"[A-Za-z0-9_.-]{1,64}")
# A DDS peer (ROS_STATIC_PEERS): a host name, an IPv4 or IPv6 address.
DDS_PEER = re.compile(r"[A-Za-z0-9][A-Za-z0-9.:-]*|\[[0-9A-Fa-f:.]+\]")
# The CA certificate of a rediss:// URL (redis.caCertificate) is written here for redis-py.
REDIS_CA_FILE = Path(os.environ.get("LIFECYCLE_REDIS_CA_FILE", "/tmp/lifecycle-redis-ca.crt"))


class ConfigError(Exception):
    pass


def log(message: str) -> None:
    print(f"config: {message}", file=sys.stderr, flush=True)


def read_config() -> dict:
    if not CONFIG_FILE.is_file():
        return {}
    try:
        data = json.loads(CONFIG_FILE.read_text(encoding="utf-8") or "{}")
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{CONFIG_FILE} is not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{CONFIG_FILE} must hold a JSON object")
    for part in ("admin", "site", "ros", "gateway", "redis"):
        if not isinstance(data.get(part, {}), dict):
            raise ConfigError(f"{CONFIG_FILE}: '{part}' must be an object")
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
    """The environment variables the configuration sets (only those with a value)."""
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


def gateway_env(config: dict, write_files: bool = False) -> dict[str, str]:
    """The gateway's own settings (parts "gateway" and "redis"): its name, the site's Redis
    URL with the gateway's credentials, the key prefix. Only the gateway role reads them, so a
    site's web and ingest never follow a Redis URL meant for its gateway. With ``write_files``
    the CA certificate of a rediss:// URL is written to REDIS_CA_FILE."""
    gateway, redis = config.get("gateway", {}), config.get("redis", {})
    env = _log_env(gateway, "gateway")
    name = _text(gateway.get("name"))
    if name:
        if not GATEWAY_NAME.fullmatch(name):
            raise ConfigError(f"gateway.name {name!r}: lower-case letters, digits, '-' and '_' (e.g. cell-a), "
                              "as registered on the site with manage.py add_gateway")
        env["LIFECYCLE_GATEWAY_NAME"] = name
    prefix = _text(gateway.get("channelPrefix"))
    if prefix:
        if not CHANNEL_PREFIX.fullmatch(prefix):
            raise ConfigError(f"gateway.channelPrefix {prefix!r}: letters, digits, '.', '_' and '-' "
                              "(the site's LIFECYCLE_CHANNEL_PREFIX, usually lifecycle)")
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
        if "-----BEGIN CERTIFICATE-----" not in certificate or "-----END CERTIFICATE-----" not in certificate:
            raise ConfigError("redis.caCertificate must be a PEM certificate (-----BEGIN CERTIFICATE----- ...)")
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


def cmd_env(role: str = "web") -> None:
    config = read_config()
    env = settings_env(config)
    if role == "gateway":
        env.update(gateway_env(config, write_files=True))
    robots_wanted(config)  # refuse a bad robot list now, in every container, with the reason
    for name, value in env.items():
        print(f"export {name}={shlex.quote(value)}")
    if CONFIG_FILE.is_file():
        log(f"read {CONFIG_FILE}" + (f" (sets {', '.join(sorted(env))})" if env else ""))
    if not os.environ.get("DJANGO_ALLOWED_HOSTS") and "DJANGO_ALLOWED_HOSTS" not in env:
        # Behind the Industrial Edge proxy the device's name is not known in advance. Only
        # the processes that serve HTTP need to say so (ingest and gateway serve none).
        if role not in ("ingest", "gateway"):
            log("WARNING: no allowed hosts configured (site.allowedHosts); accepting any Host and any "
                "WebSocket Origin. Set the device's host name to turn the origin check on.")
        print("export DJANGO_ALLOWED_HOSTS='*'")


def _django():
    import django

    os.environ.setdefault("DJANGO_SETTINGS_MODULE", "lifecycle_site.settings")
    app = os.environ.get("LIFECYCLE_APP_DIR", "/opt/lifecycle/app")
    if app not in sys.path:
        sys.path.insert(0, app)
    django.setup()


def ensure_admin(config: dict) -> None:
    from django.conf import settings
    from django.contrib.auth import get_user_model
    from django.contrib.auth.hashers import check_password, make_password
    from django.contrib.auth.models import Group
    from django.contrib.auth.password_validation import validate_password
    from django.core.exceptions import ValidationError

    admin = config.get("admin", {})
    username = _text(admin.get("username")) or os.environ.get("DJANGO_SUPERUSER_USERNAME") or "admin"
    password = admin.get("password") or os.environ.get("DJANGO_SUPERUSER_PASSWORD") or None
    email = _text(admin.get("email")) or os.environ.get("DJANGO_SUPERUSER_EMAIL", "")
    data = Path(settings.DATA_DIR)
    applied = data / ".admin-password-applied"  # hash of the configured password last applied
    users = get_user_model().objects
    user = users.filter(username=username).first()
    if password:
        try:
            validate_password(password)
        except ValidationError as exc:
            log(f"WARNING: the configured admin password is weak: {' '.join(exc.messages)}")
    if user is None:
        if not password:
            password = secrets.token_urlsafe(12)
            generated = data / "admin-password"
            generated.touch(mode=0o600)
            generated.write_text(password + "\n")
            log(f"no admin password configured: generated one, readable only inside the volume at {generated}")
        else:
            _write_private(applied, make_password(password))
        user = users.create_superuser(username, email, password)
        log(f"created the admin account {username!r}")
    elif password and not (applied.exists() and check_password(password, applied.read_text().strip())):
        user.set_password(password)
        user.is_active = True
        user.save()
        _write_private(applied, make_password(password))
        log(f"set the password of {username!r} from the configuration")
    group = Group.objects.filter(name="admin").first()
    if group is not None:
        user.groups.add(group)


def _write_private(path: Path, text: str) -> None:
    path.touch(mode=0o600)
    path.write_text(text + "\n")


def cmd_setup() -> None:
    config = read_config()
    robots = robots_wanted(config)
    _django()
    from django.core.management import call_command

    call_command("migrate", interactive=False, verbosity=1)
    ensure_admin(config)
    for robot in robots:
        call_command(
            "add_robot",
            robot["name"],
            domain=robot["domain"],
            namespace=robot["namespace"],
            description=robot["description"],
            disabled=not robot["enabled"],
            gateway=LOCAL_GATEWAY,
        )


def cmd_wait_for_schema(seconds: float) -> None:
    _django()
    from django.db import DatabaseError, connection
    from django.db.migrations.executor import MigrationExecutor

    deadline = time.monotonic() + seconds
    while True:
        try:
            executor = MigrationExecutor(connection)
            if not executor.migration_plan(executor.loader.graph.leaf_nodes()):
                return
            reason = "migrations are not applied yet"
        except DatabaseError as exc:
            reason = str(exc)
        connection.close()
        if time.monotonic() > deadline:
            raise ConfigError(
                f"the database schema is not ready after {seconds:g} s ({reason}); is the web container up?"
            )
        time.sleep(2)


def main(argv: list[str]) -> int:
    try:
        if argv[:1] == ["env"]:
            cmd_env(*argv[1:2])
        elif argv[:1] == ["setup"]:
            cmd_setup()
        elif argv[:1] == ["wait-for-schema"]:
            cmd_wait_for_schema(float(argv[1]) if len(argv) > 1 else 180)
        else:
            print(__doc__, file=sys.stderr)
            return 2
    except ConfigError as exc:
        log(f"ERROR: {exc}")
        return 78
    except Exception as exc:  # noqa: BLE001 - e.g. CommandError of add_robot: say it plainly
        from django.core.management.base import CommandError

        if isinstance(exc, CommandError):
            log(f"ERROR: {exc}")
            return 78
        raise
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
