"""The app configuration's part "signIn" (company sign-in, docs/sign-in.md) turned into the
variables LIFECYCLE_OIDC_* and LIFECYCLE_LDAP_*; the CA certificates it holds written to files.
Beside config_env.py (the rest of the file), with its checks and its ConfigError; no Django."""
from __future__ import annotations

import os
from pathlib import Path
from urllib.parse import urlsplit

from config_env import ConfigError, _check_pem, _comma_list, _text

# Company sign-in (docs/sign-in.md): the roles a directory group can give, as
# lifecycle_site/sign_in/config.py has them (ROLE_ORDER; this module imports nothing of the site).
SIGN_IN_ROLES = ("viewer", "operator", "admin")
# The CA certificates of signIn.oidc / signIn.ldap (caCertificate) are written here, and
# LIFECYCLE_OIDC_CA_FILE / LIFECYCLE_LDAP_CA_FILE point at them. Variables of their own move them
# (not LIFECYCLE_*_CA_FILE: a CA file given that way, perhaps mounted read-only, is never written over).
OIDC_CA_FILE = Path(os.environ.get("LIFECYCLE_CONFIG_OIDC_CA_FILE", "/tmp/lifecycle-oidc-ca.crt"))
LDAP_CA_FILE = Path(os.environ.get("LIFECYCLE_CONFIG_LDAP_CA_FILE", "/tmp/lifecycle-ldap-ca.crt"))
# signIn.oidc and signIn.ldap: key -> variable (caCertificate apart: a PEM, written to a file).
OIDC_KEYS = {
    "clientId": "LIFECYCLE_OIDC_CLIENT_ID",
    "clientSecret": "LIFECYCLE_OIDC_CLIENT_SECRET",
    "issuerUrl": "LIFECYCLE_OIDC_ISSUER",
    "authorizationUrl": "LIFECYCLE_OIDC_AUTHORIZATION_URL",
    "tokenUrl": "LIFECYCLE_OIDC_TOKEN_URL",
    "userinfoUrl": "LIFECYCLE_OIDC_USERINFO_URL",
    "jwksUrl": "LIFECYCLE_OIDC_JWKS_URL",
    "logoutUrl": "LIFECYCLE_OIDC_LOGOUT_URL",
    "roles": "LIFECYCLE_OIDC_ROLES",
    "groupsClaim": "LIFECYCLE_OIDC_GROUPS_CLAIM",
    "buttonName": "LIFECYCLE_OIDC_NAME",
}
LDAP_KEYS = {
    "url": "LIFECYCLE_LDAP_URL",
    "userBase": "LIFECYCLE_LDAP_USER_BASE",
    "groupBase": "LIFECYCLE_LDAP_GROUP_BASE",
    "roles": "LIFECYCLE_LDAP_ROLES",
    "adDomain": "LIFECYCLE_LDAP_AD_DOMAIN",
    "bindUser": "LIFECYCLE_LDAP_BIND_USER",
    "bindPassword": "LIFECYCLE_LDAP_BIND_PASSWORD",
}
OIDC_URL_KEYS = ("issuerUrl", "authorizationUrl", "tokenUrl", "userinfoUrl", "jwksUrl", "logoutUrl")


def sign_in_env(config: dict, write_files: bool = False) -> dict[str, str]:
    """Company sign-in (part "signIn": "oidc" and "ldap") as the variables of docs/sign-in.md.

    What can be checked without the site is checked here, with the key's name: the URLs'
    schemes, the roles, the certificates, and that a provider or directory that is switched on
    has what it needs (from here or from the environment). The site checks the rest at start."""
    sign_in = _object(config.get("signIn"), "signIn")
    oidc, ldap = _object(sign_in.get("oidc"), "signIn.oidc"), _object(sign_in.get("ldap"), "signIn.ldap")
    env: dict[str, str] = {}
    for part, keys, where in ((oidc, OIDC_KEYS, "signIn.oidc"), (ldap, LDAP_KEYS, "signIn.ldap")):
        for key, name in keys.items():
            if key == "roles":
                value = _roles(part.get(key), f"{where}.roles")
            elif key == "url":
                value = _ldap_urls(part.get(key), f"{where}.url")
            elif key in OIDC_URL_KEYS:
                value = _http_url(part.get(key), f"{where}.{key}")
            else:
                value = _text(part.get(key))
            if value:
                env[name] = value
    hours = sign_in.get("sessionHours")
    if hours not in (None, ""):
        env["LIFECYCLE_DIRECTORY_SESSION_HOURS"] = _bounded(hours, "signIn.sessionHours", 336, "hours",
                                                            "336 (two weeks), e.g. 8")
    days = sign_in.get("tokenDays")
    if days not in (None, ""):
        env["LIFECYCLE_DIRECTORY_TOKEN_DAYS"] = _bounded(days, "signIn.tokenDays", 3650, "days", "3650, e.g. 30")
    if env.get("LIFECYCLE_OIDC_CLIENT_ID"):
        # The issuer stands for the four endpoints (read from its discovery document).
        by_issuer = env.get(OIDC_KEYS["issuerUrl"]) or os.environ.get(OIDC_KEYS["issuerUrl"], "").strip()
        _needed(env, OIDC_KEYS, "signIn.oidc", "clientId", ("clientSecret", "roles"))
        if not by_issuer:
            try:
                _needed(env, OIDC_KEYS, "signIn.oidc", "clientId", ("authorizationUrl", "tokenUrl", "userinfoUrl",
                                                                    "jwksUrl"))
            except ConfigError as exc:
                raise ConfigError(f"{exc}, or signIn.oidc.issuerUrl instead of the four endpoints") from None
    if env.get("LIFECYCLE_LDAP_URL"):
        _needed(env, LDAP_KEYS, "signIn.ldap", "url", ("userBase", "roles"))
    certificates = []
    for part, path, name, where in ((oidc, OIDC_CA_FILE, "LIFECYCLE_OIDC_CA_FILE", "signIn.oidc"),
                                    (ldap, LDAP_CA_FILE, "LIFECYCLE_LDAP_CA_FILE", "signIn.ldap")):
        certificate = _text(part.get("caCertificate"))
        if certificate:
            _check_pem(certificate, f"{where}.caCertificate")
            certificates.append((path, certificate))
            env[name] = str(path)
    if write_files:  # only once everything is checked
        for path, certificate in certificates:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(certificate + "\n")
    return env


def _bounded(value, key: str, most: float, unit: str, example: str) -> str:
    """signIn.sessionHours, signIn.tokenDays: a number more than 0 and at most ``most`` (as the site reads it)."""
    try:
        number = float(value)
        if isinstance(value, bool) or not 0 < number <= most:
            raise ValueError
    except (TypeError, ValueError):
        raise ConfigError(f"{key} must be a number of {unit}, more than 0 and at most {example}") from None
    return f"{number:g}"


def _object(value, where: str) -> dict:
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise ConfigError(f"{where} must be an object")
    return value


def _needed(env: dict[str, str], keys: dict[str, str], where: str, switch: str, needed: tuple[str, ...]) -> None:
    """A provider or directory switched on here needs these keys, here or in the environment."""
    missing = [f"{where}.{key}" for key in needed
               if not env.get(keys[key]) and not os.environ.get(keys[key], "").strip()]
    if missing:
        raise ConfigError(f"{where}.{switch} is set, so sign-in needs {', '.join(missing)} as well (docs/sign-in.md)")


def _http_url(value, where: str) -> str:
    """An OpenID provider's endpoint: https:// (http:// for a provider on a trusted network)."""
    url = _text(value)
    if not url:
        return ""
    if _scheme(url) not in ("https", "http"):
        raise ConfigError(f"{where} {url!r} must be an https:// URL with a host name (http:// only on a trusted "
                          "network), as the provider's discovery document names it")
    return url


def _scheme(url: str) -> str:
    """The URL's scheme in lower case; "" when it names no host or its port is not a number."""
    try:
        parts = urlsplit(url)
        parts.port  # noqa: B018 - raises ValueError for a port that is not a number
    except ValueError:
        return ""
    return parts.scheme.lower() if parts.hostname else ""


def _ldap_urls(value, where: str) -> str:
    """``ldaps://dir.plant:636`` or ``ldap://dir.plant:389`` (StartTLS); several, all of one kind."""
    urls = [u for u in _comma_list(value).split(",") if u]
    schemes = set()
    for url in urls:
        scheme = _scheme(url)
        if scheme not in ("ldaps", "ldap"):
            raise ConfigError(f"{where} {url!r} must look like ldaps://dir.plant:636 or ldap://dir.plant:389 "
                              "(StartTLS)")
        schemes.add(scheme)
    if len(schemes) > 1:
        raise ConfigError(f"{where}: all servers must be ldaps:// or all ldap:// (StartTLS), not both")
    return ",".join(urls)


def _roles(value, where: str) -> str:
    """Groups -> roles as ``role=group,group;role=group`` (LIFECYCLE_*_ROLES), from that text or
    from an object {"viewer": ["staff"], "operator": ["g2", "g3"], "admin": "plant-it"}."""
    if value is None or value == "":
        return ""
    pairs: list[tuple[str, list[str]]] = []
    if isinstance(value, dict):
        for role, groups in value.items():
            if isinstance(groups, list):
                names = [_text(g) for g in groups]
                if any("," in g or ";" in g for g in names):
                    raise ConfigError(f"{where}.{role}: a group name cannot hold ',' or ';'")
            elif isinstance(groups, str) or groups is None:
                names = _text(groups).split(",")
                if any(";" in g for g in names):
                    raise ConfigError(f"{where}.{role}: separate groups with ',' (not ';')")
            else:
                raise ConfigError(f"{where}.{role} must be a list of group names")
            pairs.append((str(role), names))
    elif isinstance(value, str):
        for part in filter(None, (p.strip() for p in value.split(";"))):
            role, sep, groups = part.partition("=")
            if not sep:
                raise ConfigError(f"{where} {value!r}: expected role=group,group;role=group "
                                  "(e.g. operator=lifecycle-operators;admin=plant-it)")
            pairs.append((role, groups.split(",")))
    else:
        raise ConfigError(f"{where} must be text (role=group,group;role=group) or an object "
                          '{"viewer": [...], "operator": [...], "admin": [...]}')
    seen: dict[str, str] = {}
    parts = []
    for role, groups in pairs:
        role = role.strip().lower()
        if role not in SIGN_IN_ROLES:
            raise ConfigError(f"{where}: {role!r} is not a role; the roles are {', '.join(SIGN_IN_ROLES)}")
        groups = [g.strip() for g in groups if g.strip()]
        for group in groups:
            first = seen.setdefault(group.lower(), role)
            if first != role:
                raise ConfigError(f"{where}: the group {group!r} is mapped to two roles ({first}, {role})")
        if groups:
            parts.append(f"{role}={','.join(groups)}")
    return ";".join(parts)
