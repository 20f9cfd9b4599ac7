"""A request whose values the database cannot take is the client's error (400), not the site's.

SQLite stores what PostgreSQL refuses: a NUL character in text (a node key %00 in a URL), a
value longer than its column (a node name of 300 characters). On PostgreSQL the query raises
DataError; the API answers it with its JSON error (lifecycle_site/api/auth.py), and this
middleware answers it everywhere else, instead of a server error."""
from __future__ import annotations

import logging

from django.db import DataError
from django.http import HttpRequest, HttpResponse, HttpResponseBadRequest
from django.utils.deprecation import MiddlewareMixin

log = logging.getLogger(__name__)

MESSAGE = ("The request holds a value the database cannot store (a NUL character, or text longer than "
           "the field allows). Correct it and send it again.")


class DatabaseInputMiddleware(MiddlewareMixin):
    def process_exception(self, request: HttpRequest, exception: Exception) -> HttpResponse | None:
        if not isinstance(exception, DataError):
            return None
        log.warning("%s %r refused (400): %s", request.method, request.path, str(exception).splitlines()[0])
        return HttpResponseBadRequest(MESSAGE, content_type="text/plain; charset=utf-8")
