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
import threading
import time
from concurrent.futures import ThreadPoolExecutor

from asgiref.sync import sync_to_async
from django.core import signals
from django.core.exceptions import RequestAborted
from django.core.handlers.asgi import ASGIHandler, get_script_prefix
from django.db import connections
from django.http import HttpRequest, HttpResponseBase
from django.urls import set_script_prefix

from lifecycle_site.ingest import live_updates
from ros_gateway.shared import environment

# Requests served at once. A transition waits for its gateway (seconds, if a node hangs), so
# the pool is wide; threads (and their connections) are only made when all others are busy.
# Lower it where the database limits connections: PostgreSQL's max_connections must cover
# WORKERS x site instances + the ingest process and commands (docker/README.md).
WORKERS = environment.whole("LIFECYCLE_HTTP_WORKERS", 64, minimum=1, maximum=1024, unit="threads")
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

    async def handle(self, scope, receive, send) -> None:
        """Django's ASGI request cycle, with the view's work in one call to ``self.workers``.

        Django runs each request in a ThreadSensitiveContext (``ASGIHandler.__call__``), which
        gives the request a thread of its own once it makes a thread-sensitive call. Django's
        own cycle makes two, its request_started receivers and ``response.close()``, so every
        request started a thread, on the event loop, which waited for it to run (under load
        several ms, ~100 times a second) and joined it after. Those calls are Django's own
        receivers (reset_queries, close_old_connections, close_caches), which touch nothing on
        the event loop's thread, so here they run there: only a streaming answer (sent through
        ``sync_to_async``) still gets a thread. Nor does this listen for the client going away
        while the view runs: a synchronous view cannot be stopped."""
        try:
            body_file = await self.read_body(receive)
        except RequestAborted:
            return
        set_script_prefix(get_script_prefix(scope))
        signals.request_started.send(sender=self.__class__, scope=scope)
        request, error_response = self.create_request(scope, body_file)
        response = error_response if request is None else await self.run_get_response(request)
        try:
            await self.send_response(response, send)
        except asyncio.CancelledError:
            pass  # the client went away while the answer was sent
        finally:
            response.close()  # request_finished
            body_file.close()

    def respond(self, request: HttpRequest) -> HttpResponseBase:
        _keep_or_close_connections()
        return self.get_response(request)

    async def get_response_async(self, request: HttpRequest) -> HttpResponseBase:
        live_updates.server_loop.set(asyncio.get_running_loop())  # copied into the worker's context
        return await sync_to_async(self.respond, thread_sensitive=False, executor=self.workers)(request)
