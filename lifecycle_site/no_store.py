"""Answers about the fleet are not kept by browsers or proxies: plant PCs are shared, and a
page or an API answer cached on disk outlives the logout. Static files (served by WhiteNoise
before this middleware runs) stay cacheable."""
from __future__ import annotations

from django.http import HttpRequest, HttpResponse
from django.utils.cache import add_never_cache_headers
from django.utils.deprecation import MiddlewareMixin


class NoStoreMiddleware(MiddlewareMixin):
    def process_response(self, request: HttpRequest, response: HttpResponse) -> HttpResponse:
        if not response.has_header("Cache-Control"):
            add_never_cache_headers(response)  # no-cache, no-store, must-revalidate, private
        return response
