"""The OpenID provider's endpoints: those set one by one (LIFECYCLE_OIDC_*_URL), the rest read from
its discovery document (``LIFECYCLE_OIDC_ISSUER``/.well-known/openid-configuration, OpenID Connect
Discovery 1.0) when a sign-in needs them, not at start: a provider that is down while the site
starts costs only the sign-ins tried meanwhile, which are refused in words.

The document is a stranger's answer: it is read with the sign-in's time-out and certificate
rules, at most MAX_DOCUMENT_BYTES, its ``issuer`` must be the one configured (section 4.3), and
each endpoint must be an http(s) URL (https when the issuer is). Kept DOCUMENT_TTL_S once read.
"""
from __future__ import annotations

import json
import logging
import threading
import time
from urllib.parse import urlsplit

import requests
import urllib3
from django.conf import settings

from lifecycle_site.sign_in import problems
from lifecycle_site.sign_in.config import origin

log = logging.getLogger("lifecycle.sign_in")

MAX_DOCUMENT_BYTES = 256 * 1024
DOCUMENT_TTL_S = 3600.0
WELL_KNOWN = "/.well-known/openid-configuration"
# mozilla-django-oidc's setting -> the discovery document's field.
FIELDS = {
    "OIDC_OP_AUTHORIZATION_ENDPOINT": "authorization_endpoint",
    "OIDC_OP_TOKEN_ENDPOINT": "token_endpoint",
    "OIDC_OP_USER_ENDPOINT": "userinfo_endpoint",
    "OIDC_OP_JWKS_ENDPOINT": "jwks_uri",
}
END_SESSION = "end_session_endpoint"

_lock = threading.Lock()
_cached: dict = {"issuer": "", "at": 0.0, "document": None}


class DiscoveryFailed(Exception):
    """The endpoints could not be found; ``problem`` says so to the person signing in."""

    def __init__(self, problem: problems.Problem, reason: str) -> None:
        super().__init__(reason)
        self.problem = problem


def endpoints() -> dict[str, str]:
    """Every endpoint setting of FIELDS with its URL: as set, else from the discovery document.
    Raises DiscoveryFailed."""
    found = {name: getattr(settings, name, "") or "" for name in FIELDS}
    missing = [name for name, url in found.items() if not url]
    if missing:
        document = _document()
        for name in missing:
            found[name] = _endpoint(document, FIELDS[name])
    return found


def end_session_url() -> str:
    """Where Log out sends the browser to end the provider's session too: as set, else the
    document's end_session_endpoint if it is on the issuer's origin (the only other origin the
    page's Content-Security-Policy lets a form go to); "" for none, or while the document cannot
    be read (Log out then ends the site's session only)."""
    configured = getattr(settings, "OIDC_OP_END_SESSION_URL", "") or ""
    issuer = getattr(settings, "OIDC_OP_ISSUER", "") or ""
    if configured or not issuer:
        return configured
    try:
        url = _endpoint(_document(), END_SESSION, required=False)
    except Exception as exc:  # noqa: BLE001 - whatever the provider does, Log out still ends the site's session
        log.warning("Log out ends the site's session only: %s", exc)
        return ""
    if url and origin(url) != origin(issuer):
        log.warning("the provider's end_session_endpoint %s is not on the issuer's origin %s: set "
                    "LIFECYCLE_OIDC_LOGOUT_URL to use it", url, origin(issuer))
        return ""
    return url


def forget() -> None:
    """Read the document again at its next use (tests; a provider moved)."""
    with _lock:
        _cached.update(issuer="", at=0.0, document=None)


def _document() -> dict:
    issuer = getattr(settings, "OIDC_OP_ISSUER", "") or ""
    if not issuer:
        raise DiscoveryFailed(problems.PROVIDER_ANSWER_INVALID,
                              "an endpoint is not set and LIFECYCLE_OIDC_ISSUER is not either")
    with _lock:
        if _cached["issuer"] == issuer and time.monotonic() - _cached["at"] < DOCUMENT_TTL_S:
            return _cached["document"]
    document = _read(issuer)
    with _lock:
        _cached.update(issuer=issuer, at=time.monotonic(), document=document)
    return document


def _read(issuer: str) -> dict:
    url = issuer + WELL_KNOWN
    try:
        body = _download(url)
    except requests.exceptions.HTTPError as exc:
        if exc.response is not None and exc.response.status_code >= 500:  # the provider is down or starting
            log.warning("OIDC discovery document %s could not be read: %s", url, exc)
            raise DiscoveryFailed(problems.PROVIDER_UNREACHABLE, f"{url} answered {exc}") from None
        raise _invalid(url, f"it answered {exc}") from None
    except (requests.exceptions.RequestException, urllib3.exceptions.HTTPError, OSError) as exc:
        log.warning("OIDC discovery document %s could not be read: %s", url, exc)
        raise DiscoveryFailed(problems.PROVIDER_UNREACHABLE, f"{url} could not be read: {exc}") from None
    if len(body) > MAX_DOCUMENT_BYTES:
        raise _invalid(url, f"it is larger than {MAX_DOCUMENT_BYTES:,} bytes")
    try:
        document = json.loads(body)
    except (ValueError, RecursionError):
        raise _invalid(url, "it is not JSON") from None
    if not isinstance(document, dict):
        raise _invalid(url, "it is not a JSON object")
    named = document.get("issuer")
    # Exactly the issuer configured (section 4.3), but for a trailing slash, which the setting
    # does not keep and some providers' issuers have (Auth0's).
    if not isinstance(named, str) or named.rstrip("/") != issuer:
        raise _invalid(url, f"it names the issuer {str(document.get('issuer'))[:200]!r}, not {issuer!r} "
                            "(LIFECYCLE_OIDC_ISSUER must be exactly the provider's issuer)")
    return document


def _download(url: str) -> bytes:
    """The document's bytes, at most MAX_DOCUMENT_BYTES + 1 of them, within OIDC_TIMEOUT in all (a
    provider that drips its answer is cut off, not waited for; a compressed one is not JSON)."""
    timeout = settings.OIDC_TIMEOUT
    deadline = time.monotonic() + timeout
    # Asked plain (identity): decoding a compressed answer could read on without returning a byte.
    with requests.get(url, timeout=timeout, verify=settings.OIDC_VERIFY_SSL, stream=True, allow_redirects=False,
                      headers={"Accept-Encoding": "identity"}) as answer:
        answer.raise_for_status()
        body = bytearray()
        while len(body) <= MAX_DOCUMENT_BYTES:
            if time.monotonic() > deadline:
                raise requests.exceptions.Timeout(f"the document took longer than {timeout:g} s")
            chunk = answer.raw.read1(64 * 1024, decode_content=False)
            if not chunk:
                break
            body += chunk
    return bytes(body)


def _endpoint(document: dict, field: str, required: bool = True) -> str:
    issuer = settings.OIDC_OP_ISSUER
    url = document.get(field)
    if url is None and not required:
        return ""
    schemes = ("https",) if issuer.startswith("https://") else ("http", "https")
    try:
        parts = urlsplit(url) if isinstance(url, str) else None
    except ValueError:  # e.g. "https://[::1/x"
        parts = None
    if parts is None or parts.scheme not in schemes or not parts.netloc:
        raise _invalid(issuer + WELL_KNOWN, f"its {field} is not an {' or '.join(schemes)} URL: "
                                            f"{str(url)[:200]!r}")
    return url


def _invalid(url: str, reason: str) -> DiscoveryFailed:
    log.warning("OIDC discovery document %s refused: %s", url, reason)
    return DiscoveryFailed(problems.PROVIDER_ANSWER_INVALID, f"{url}: {reason}")
