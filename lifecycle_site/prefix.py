"""Serving under a sub-path chosen by a reverse proxy (Industrial Edge: /<app-name>/).

The proxy strips the prefix, so requests arrive at "/...". Links must still carry it:
either a fixed prefix (LIFECYCLE_URL_PREFIX, applied through Django's FORCE_SCRIPT_NAME)
or, when LIFECYCLE_TRUST_FORWARDED_PREFIX is on, the proxy's X-Forwarded-Prefix header.
"""
from __future__ import annotations

import re
from contextlib import contextmanager
from typing import Iterator

from django.conf import settings
from django.contrib.staticfiles.storage import StaticFilesStorage
from django.http import HttpRequest
from django.urls import get_script_prefix, set_script_prefix

VALID_PREFIX = re.compile(r"^(/[A-Za-z0-9._~-]+)+$")


def forwarded_prefix(header_value: str | None) -> str | None:
    """The proxy's prefix ('/lifecycle'), if trusted and well-formed."""
    if not settings.LIFECYCLE_TRUST_FORWARDED_PREFIX or not header_value:
        return None
    prefix = header_value.strip().rstrip("/")
    return prefix if VALID_PREFIX.match(prefix) else None


@contextmanager
def script_prefix(prefix: str | None) -> Iterator[None]:
    """Render links under ``prefix`` (for WebSocket fragments, rendered outside a request)."""
    if not prefix:
        yield
        return
    previous = get_script_prefix()
    set_script_prefix(prefix + "/")
    try:
        yield
    finally:
        set_script_prefix(previous)


class ForwardedPrefixMiddleware:
    """Puts the prefix into request.path and reversed URLs. Django's FORCE_SCRIPT_NAME alone
    leaves request.path without it under ASGI, so ?next= links would lose the prefix."""

    def __init__(self, get_response) -> None:
        self.get_response = get_response

    def __call__(self, request: HttpRequest):
        prefix = forwarded_prefix(request.headers.get("X-Forwarded-Prefix")) or settings.URL_PREFIX
        if not prefix:
            return self.get_response(request)
        request.META["SCRIPT_NAME"] = prefix
        request.path = prefix + request.path_info
        with script_prefix(prefix):  # never leaks one request's prefix into the next
            return self.get_response(request)


class PrefixedStaticFilesStorage(StaticFilesStorage):
    """Static URLs under the current request's prefix (the stock storage fixes it at start-up)."""

    @property
    def base_url(self) -> str:
        return get_script_prefix() + settings.STATIC_URL_PATH
