"""Django's HTTP handling under daphne: the middleware run as one synchronous chain, in a pool
of worker threads that keep their database connections.

Django's own ASGI handler runs the middleware in async mode. Each of ours that is written the
classic way (Django's security, session, CSRF, auth, messages and clickjacking middleware
among them) then hands its request and its response to a worker thread and back: about twenty
thread switches for every request. All our views are synchronous, so here the whole chain and
the view run in one call, in one worker thread.

Django also opens a new database connection for each request under ASGI (a new thread each
time): with SQLite that is ~1 ms, most of it reading the schema again. The workers here keep
theirs from one request to the next, and close one that failed, was left in a transaction or
has been open for CONNECTION_LIFETIME_S. docs/performance.md has the figures.
"""
from __future__ import annotations

import asyncio
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor

from asgiref.sync import sync_to_async
from django.core.handlers.asgi import ASGIHandler
from django.db import connections
from django.http import HttpRequest, HttpResponseBase

from lifecycle_site.fleet import live_updates

# Requests served at once. A transition waits for its gateway (seconds, if a node hangs), so
# the pool is wide; threads (and their connections) are only made when all others are busy.
# Lower it where the database limits connections: PostgreSQL's max_connections must cover
# WORKERS x site instances + the ingest process and commands (docker/README.md).
WORKERS = int(os.environ.get("LIFECYCLE_HTTP_WORKERS", "64"))
CONNECTION_LIFETIME_S = 300.0

_opened = threading.local()  # per worker: connection alias -> when this thread opened it


def _keep_or_close_connections() -> None:
    """Before a request: keep this thread's connections open unless they cannot be trusted."""
    opened: dict[str, float] = _opened.__dict__.setdefault("at", {})
    now = time.monotonic()
    for connection in connections.all(initialized_only=True):
        if connection.connection is None:
            opened.pop(connection.alias, None)
            continue
        since = opened.setdefault(connection.alias, now)
        if (connection.errors_occurred or connection.in_atomic_block or not connection.get_autocommit()
                or now - since > CONNECTION_LIFETIME_S):
            connection.close()
            opened.pop(connection.alias, None)


class SyncChainHandler(ASGIHandler):
    def __init__(self) -> None:
        super().__init__()
        self.workers = ThreadPoolExecutor(max_workers=WORKERS, thread_name_prefix="http")

    def load_middleware(self, is_async: bool = False) -> None:
        super().load_middleware(is_async=False)

    def respond(self, request: HttpRequest) -> HttpResponseBase:
        _keep_or_close_connections()
        return self.get_response(request)

    async def get_response_async(self, request: HttpRequest) -> HttpResponseBase:
        live_updates.server_loop.set(asyncio.get_running_loop())  # copied into the worker's context
        return await sync_to_async(self.respond, thread_sensitive=False, executor=self.workers)(request)
