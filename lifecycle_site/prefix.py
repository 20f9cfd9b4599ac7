"""Serving under a sub-path chosen by a reverse proxy (Industrial Edge: /<app-name>/).

The proxy strips the prefix, so requests arrive at "/...". Links must still carry it:
either a fixed prefix (LIFECYCLE_URL_PREFIX, applied through Django's FORCE_SCRIPT_NAME)
or, when LIFECYCLE_TRUST_FORWARDED_PREFIX is on, the proxy's X-Forwarded-Prefix header.
"""
from __future__ import annotations

import re

from django.conf import settings
from django.contrib.staticfiles.storage import StaticFilesStorage
from django.http import HttpRequest
from django.urls import get_script_prefix, set_script_prefix

VALID_PREFIX = re.compile(r"^(/[A-Za-z0-9._~-]+)+$")


class ForwardedPrefixMiddleware:
    def __init__(self, get_response) -> None:
        self.get_response = get_response

    def __call__(self, request: HttpRequest):
        if not settings.LIFECYCLE_TRUST_FORWARDED_PREFIX:
            return self.get_response(request)
        default = get_script_prefix()
        prefix = request.headers.get("X-Forwarded-Prefix", "").rstrip("/")
        if prefix and VALID_PREFIX.match(prefix):
            request.META["SCRIPT_NAME"] = prefix
            request.path = prefix + request.path_info
            set_script_prefix(prefix + "/")
        try:
            return self.get_response(request)
        finally:
            set_script_prefix(default)  # never leak one request's prefix into the next


class PrefixedStaticFilesStorage(StaticFilesStorage):
    """Static URLs under the current request's prefix (the stock storage fixes it at start-up)."""

    @property
    def base_url(self) -> str:
        return get_script_prefix() + settings.STATIC_URL_PATH
