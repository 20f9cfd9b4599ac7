"""Company sign-in settings from the environment: which of OIDC and LDAP are on, and the Django
settings their libraries read (mozilla-django-oidc, django-python3-ldap). Read by settings.py;
nothing here imports Django models. Every variable is described in docs/sign-in.md."""
from __future__ import annotations

import os
from collections.abc import Mapping
from urllib.parse import urlsplit

from ros_gateway.shared import environment as env
from ros_gateway.shared.environment import SettingError

ROLE_ORDER = ("viewer", "operator", "admin")  # lowest first: a member of several groups gets the highest


def role_mapping(name: str, environ: Mapping[str, str] | None = None) -> dict[str, str]:
    """``admin=plant-it;operator=shift-leads,operators;viewer=staff`` as {group (lower case): role}.

    Group names are compared without regard to case (directories differ in what they keep)."""
    raw = env.text(name, "", environ)
    mapping: dict[str, str] = {}
    for part in filter(None, (p.strip() for p in raw.split(";"))):
        role, sep, groups = part.partition("=")
        role = role.strip().lower()
        if not sep or role not in ROLE_ORDER:
            raise SettingError(f"{name}={raw!r}: expected role=group,group;role=group with the roles "
                               f"viewer, operator and admin (e.g. 'operator=lifecycle-operators;admin=plant-it').")
        for group in filter(None, (g.strip().lower() for g in groups.split(","))):
            if mapping.get(group, role) != role:
                raise SettingError(f"{name}: the group {group!r} is mapped to two roles ({mapping[group]}, {role}).")
            mapping[group] = role
    return mapping


def _required(names: list[str], what: str, environ: Mapping[str, str] | None) -> None:
    missing = [n for n in names if not env.text(n, "", environ)]
    if missing:
        raise SettingError(f"{what} needs {', '.join(missing)} as well.")


def oidc_settings(environ: Mapping[str, str] | None = None) -> dict:
    """mozilla-django-oidc's settings, or {} when LIFECYCLE_OIDC_CLIENT_ID is not set."""
    if not env.text("LIFECYCLE_OIDC_CLIENT_ID", "", environ):
        return {}
    issuer = _issuer(environ)
    endpoints = [] if issuer else ["LIFECYCLE_OIDC_AUTHORIZATION_URL", "LIFECYCLE_OIDC_TOKEN_URL",
                                   "LIFECYCLE_OIDC_USERINFO_URL", "LIFECYCLE_OIDC_JWKS_URL"]
    _required(["LIFECYCLE_OIDC_CLIENT_SECRET", *endpoints, "LIFECYCLE_OIDC_ROLES"],
              "Sign-in with OIDC (LIFECYCLE_OIDC_CLIENT_ID is set)" + (
                  "" if issuer else " without LIFECYCLE_OIDC_ISSUER (whose discovery document names the endpoints)"),
              environ)
    ca_file = env.text("LIFECYCLE_OIDC_CA_FILE", "", environ)
    return {
        "OIDC_RP_CLIENT_ID": env.text("LIFECYCLE_OIDC_CLIENT_ID", "", environ),
        "OIDC_RP_CLIENT_SECRET": env.text("LIFECYCLE_OIDC_CLIENT_SECRET", "", environ),
        "OIDC_OP_ISSUER": issuer,  # endpoints not set are read from its discovery document (sign_in.discovery)
        "OIDC_OP_AUTHORIZATION_ENDPOINT": env.text("LIFECYCLE_OIDC_AUTHORIZATION_URL", "", environ),
        "OIDC_OP_TOKEN_ENDPOINT": env.text("LIFECYCLE_OIDC_TOKEN_URL", "", environ),
        "OIDC_OP_USER_ENDPOINT": env.text("LIFECYCLE_OIDC_USERINFO_URL", "", environ),
        "OIDC_OP_JWKS_ENDPOINT": env.text("LIFECYCLE_OIDC_JWKS_URL", "", environ),
        "OIDC_OP_END_SESSION_URL": env.text("LIFECYCLE_OIDC_LOGOUT_URL", "", environ),
        "OIDC_RP_SIGN_ALGO": env.text("LIFECYCLE_OIDC_SIGN_ALGO", "RS256", environ),
        "OIDC_RP_SCOPES": env.text("LIFECYCLE_OIDC_SCOPES", "openid email profile", environ),
        "OIDC_USE_PKCE": True,
        "OIDC_PKCE_CODE_CHALLENGE_METHOD": "S256",
        "OIDC_STORE_ID_TOKEN": True,  # the hint for the provider's logout
        "OIDC_TIMEOUT": env.number("LIFECYCLE_OIDC_TIMEOUT", 5.0, above=0, environ=environ),
        "OIDC_VERIFY_SSL": ca_file or True,  # requests' verify: a CA bundle path, or the system's
        "LIFECYCLE_OIDC_GROUPS_CLAIM": env.text("LIFECYCLE_OIDC_GROUPS_CLAIM", "groups", environ),
        "LIFECYCLE_OIDC_ROLES": role_mapping("LIFECYCLE_OIDC_ROLES", environ),
        "LIFECYCLE_OIDC_NAME": env.text("LIFECYCLE_OIDC_NAME", "", environ),  # "": "company account", translated
    }


def _issuer(environ: Mapping[str, str] | None) -> str:
    """LIFECYCLE_OIDC_ISSUER without a trailing slash ("" when not set), an http(s) URL."""
    raw = env.text("LIFECYCLE_OIDC_ISSUER", "", environ).strip()
    if not raw:
        return ""
    parts = urlsplit(raw)
    if parts.scheme not in ("http", "https") or not parts.netloc or parts.query or parts.fragment:
        raise SettingError(f"LIFECYCLE_OIDC_ISSUER={raw!r}: expected the provider's issuer, an https URL without a "
                           "query, e.g. https://login.example.com/realms/plant")
    return raw.rstrip("/")


def ldap_settings(environ: Mapping[str, str] | None = None) -> dict:
    """django-python3-ldap's settings, or {} when LIFECYCLE_LDAP_URL is not set.

    Always over TLS: ``ldaps://`` as it is, ``ldap://`` with StartTLS; the server's certificate is
    checked against LIFECYCLE_LDAP_CA_FILE (else the system's CAs)."""
    urls = env.items("LIFECYCLE_LDAP_URL", "", environ)
    if not urls:
        return {}
    _required(["LIFECYCLE_LDAP_USER_BASE", "LIFECYCLE_LDAP_ROLES"], "Sign-in with LDAP (LIFECYCLE_LDAP_URL is set)",
              environ)
    schemes = {url.split("://", 1)[0].lower() for url in urls}
    if not schemes <= {"ldap", "ldaps"} or len(schemes) > 1:
        raise SettingError(f"LIFECYCLE_LDAP_URL={','.join(urls)!r}: expected ldaps://host:636 or ldap://host:389 "
                           "(StartTLS), all of one kind.")
    import ssl  # only when LDAP is on

    ca_file = env.text("LIFECYCLE_LDAP_CA_FILE", "", environ)
    if ca_file and not os.path.isfile(ca_file):
        raise SettingError(f"LIFECYCLE_LDAP_CA_FILE={ca_file!r}: no such file.")
    import ldap3

    tls_args = {"validate": ssl.CERT_REQUIRED, "ca_certs_file": ca_file or None}
    ad_domain = env.text("LIFECYCLE_LDAP_AD_DOMAIN", "", environ)
    attribute = env.text("LIFECYCLE_LDAP_USER_ATTRIBUTE", "sAMAccountName" if ad_domain else "uid", environ)
    # Whole seconds: ldap3 packs the receive timeout into a socket option as an integer.
    timeout = env.whole("LIFECYCLE_LDAP_TIMEOUT", 5, minimum=1, maximum=120, unit="seconds", environ=environ)
    return {
        "LDAP_AUTH_URL": urls,
        "LDAP_AUTH_USE_TLS": "ldap" in schemes,  # StartTLS on a plain port
        "LDAP_AUTH_CONNECT_USE_SSL": "ldaps" in schemes,
        "LDAP_AUTH_TLS_ARGS": tls_args,
        # For ldaps:// the library passes no Tls of its own, and ldap3's default checks no certificate.
        "LDAP_AUTH_CONNECT_ARGS": {"tls": ldap3.Tls(**tls_args)} if "ldaps" in schemes else {},
        "LDAP_AUTH_SEARCH_BASE": env.text("LIFECYCLE_LDAP_USER_BASE", "", environ),
        "LDAP_AUTH_OBJECT_CLASS": env.text("LIFECYCLE_LDAP_USER_CLASS", "user" if ad_domain else "inetOrgPerson",
                                           environ),
        "LDAP_AUTH_USER_FIELDS": {"username": attribute, "first_name": "givenName", "last_name": "sn",
                                  "email": "mail"},
        "LDAP_AUTH_USER_LOOKUP_FIELDS": ("username",),
        "LDAP_AUTH_CLEAN_USER_DATA": "lifecycle_site.sign_in.ldap.clean_user_data",
        "LDAP_AUTH_SYNC_USER_RELATIONS": "lifecycle_site.sign_in.ldap.give_role",
        "LDAP_AUTH_ACTIVE_DIRECTORY_DOMAIN": ad_domain or None,
        # The service account is bound as it is set (a DN or NAME@DOMAIN); users as the library forms it.
        "LDAP_AUTH_FORMAT_USERNAME": "lifecycle_site.sign_in.ldap.bind_name",
        "SIGN_IN_LDAP_USER_FORMAT": ("django_python3_ldap.utils.format_username_active_directory_principal"
                                           if ad_domain else "django_python3_ldap.utils.format_username_openldap"),
        "LDAP_AUTH_CONNECTION_USERNAME": env.text("LIFECYCLE_LDAP_BIND_USER", "", environ) or None,
        "LDAP_AUTH_CONNECTION_PASSWORD": env.text("LIFECYCLE_LDAP_BIND_PASSWORD", "", environ) or None,
        # One pass over the servers, then give up: ldap3's default (True) retries for ever when all are down.
        "LDAP_AUTH_POOL_ACTIVE": 1,
        "LDAP_AUTH_CONNECT_TIMEOUT": timeout,
        "LDAP_AUTH_RECEIVE_TIMEOUT": timeout,
        "LIFECYCLE_LDAP_GROUP_BASE": env.text("LIFECYCLE_LDAP_GROUP_BASE", "", environ)
        or env.text("LIFECYCLE_LDAP_USER_BASE", "", environ),
        "LIFECYCLE_LDAP_ROLES": role_mapping("LIFECYCLE_LDAP_ROLES", environ),
    }


def directory_session_hours(environ: Mapping[str, str] | None = None) -> float:
    """How long a session of a directory account lasts after its sign-in: its role comes from its
    groups at sign-in, so a group taken away in the directory takes the role away by then at the
    latest. 12 hours (a long shift) by default; local accounts keep Django's two weeks."""
    return env.number("LIFECYCLE_DIRECTORY_SESSION_HOURS", 12.0, above=0, maximum=336, unit="hours", example=8,
                      environ=environ)


def directory_token_days(environ: Mapping[str, str] | None = None) -> float:
    """How long the API tokens of a directory account keep working after its last sign-in: the
    directory is not asked when a token is used (an OpenID provider cannot be), so a person who
    left, or lost a group, is cut off by then at the latest. 30 days by default."""
    return env.number("LIFECYCLE_DIRECTORY_TOKEN_DAYS", 30.0, above=0, maximum=3650, unit="days", example=30,
                      environ=environ)


def origin(url: str) -> str:
    """``https://idp.plant:8443/realms/x/logout`` -> ``https://idp.plant:8443`` (for a CSP source)."""
    parts = urlsplit(url)
    return f"{parts.scheme}://{parts.netloc}"
