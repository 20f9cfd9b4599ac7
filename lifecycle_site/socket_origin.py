"""Only the site's own pages may open its WebSockets.

A browser sends the session cookie with a WebSocket whatever page opens it, and cookies are
per host, not per port: a page served by any other program on the same host (another app on
the device, http://127.0.0.1:9999) could otherwise read the live fleet with the user's session.
Channels' AllowedHostsOriginValidator compares only the Origin's host name with ALLOWED_HOSTS.

The rule here is Django's CSRF rule for form posts: the Origin must be the scheme, host and port
the socket was opened on (https when a trusted TLS proxy says so), or one of
CSRF_TRUSTED_ORIGINS. So wherever the forms work, the sockets do. A refused socket never opens
(the handshake is answered 403) and is on record with the other refused attempts.
"""
from __future__ import annotations

import logging
from urllib.parse import urlsplit

from channels.db import database_sync_to_async
from django.conf import settings
from django.http import HttpRequest
from django.http.request import is_same_domain, split_domain_port, validate_host

from lifecycle_site.audit import denials

log = logging.getLogger("lifecycle.denials")
DEFAULT_PORTS = {"http": 80, "https": 443}


def _normal(origin: str) -> tuple[str, str, int | None] | None:
    """(scheme, host, port) of an origin or None when it is no http(s) origin."""
    try:
        parts = urlsplit(origin.strip().lower())
        port = parts.port
    except ValueError:  # a port out of range, a bad IPv6 literal
        return None
    if parts.scheme not in DEFAULT_PORTS or not parts.hostname:
        return None
    return parts.scheme, parts.hostname, port or DEFAULT_PORTS[parts.scheme]


def _header(scope: dict, name: bytes) -> str:
    for key, value in scope.get("headers", []):
        if key == name:
            return value.decode("latin-1")
    return ""


def site_origin(scope: dict) -> str | None:
    """The origin the socket was opened on, from its Host header; None if that host is not
    one of ALLOWED_HOSTS (Django checks it for requests; Channels does not for sockets)."""
    host = _header(scope, b"host").strip()
    domain, _ = split_domain_port(host)
    if not domain or not validate_host(domain, settings.ALLOWED_HOSTS):
        return None
    secure = scope.get("scheme") == "wss"
    proxy_header = getattr(settings, "SECURE_PROXY_SSL_HEADER", None)
    if proxy_header:  # ("HTTP_X_FORWARDED_PROTO", "https"), as Django's request.is_secure() reads it
        name, value = proxy_header
        sent = _header(scope, name.removeprefix("HTTP_").replace("_", "-").lower().encode())
        secure = secure or sent.split(",", 1)[0].strip() == value
    return f"{'https' if secure else 'http'}://{host}"


def origin_allowed(origin: str, site: str | None) -> bool:
    parsed = _normal(origin)
    if parsed is None or site is None:
        return False
    if parsed == _normal(site):
        return True
    for trusted in settings.CSRF_TRUSTED_ORIGINS:
        if "*" in trusted:  # https://*.plant.example: any subdomain, as Django's CSRF check reads it
            scheme, _, netloc = trusted.partition("://")
            if parsed[0] == scheme and is_same_domain(urlsplit(origin.lower()).netloc, netloc.lstrip("*")):
                return True
        elif parsed == _normal(trusted):
            return True
    return False


def _record(scope: dict, origin: str, site: str | None) -> None:
    request = HttpRequest()
    request.method = "GET"
    request.path = scope.get("root_path", "") + scope.get("path", "")
    request.META["REMOTE_ADDR"] = (scope.get("client") or ("",))[0]
    request.user = scope.get("user")
    shown = origin[:80] or "no Origin header"
    log.warning("refused a WebSocket from %s to %s: not this site's origin; if it is this site behind a "
                "proxy, list its origin in DJANGO_CSRF_TRUSTED_ORIGINS", shown, site or "a host not allowed")
    denials.record(request, 403, "socket_origin", f"WebSocket opened by a page of {shown}; this site is "
                                                  f"{site or 'not reached by an allowed host name'}")


class SameOriginValidator:
    """ASGI middleware for the "websocket" scope: lets through sockets of the site's own
    pages, refuses the others. Inside AuthMiddlewareStack, so a refusal names the account whose
    cookie came along."""

    def __init__(self, application) -> None:
        self.application = application

    async def __call__(self, scope: dict, receive, send):
        origin = _header(scope, b"origin")
        site = site_origin(scope)
        if origin_allowed(origin, site):
            return await self.application(scope, receive, send)
        await database_sync_to_async(_record)(scope, origin, site)
        await refuse(receive, send)


async def refuse(receive, send) -> None:
    """Close the socket before accepting it: the server answers the handshake 403. Nothing is
    held for it after that (Channels' WebsocketDenier is a consumer with a channel-layer channel
    of its own: a Redis read that lingered up to daphne's 10 s after each refusal)."""
    if (await receive())["type"] == "websocket.connect":
        await send({"type": "websocket.close"})
