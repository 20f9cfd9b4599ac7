"""Telling open pages what was stored: the live updates sent through the Channels layer after
facts are applied (by the ingest process and by the request path)."""
from __future__ import annotations

import asyncio
import logging
import threading
from concurrent.futures import Future
from contextvars import ContextVar
from typing import Any, Iterable, Sequence

from channels.layers import get_channel_layer

from lifecycle_site.audit.models import ParameterRecord, TransitionRecord
from ros_gateway.shared import protocol

log = logging.getLogger(__name__)

# Open audit history pages (dashboard/audit_consumer.py): told that records were stored, they
# read what is new through their own filter.
AUDIT_GROUP = "audit"
# The word to them: they read what is new themselves.
AUDIT_STORED = (AUDIT_GROUP, {"type": "audit.record", "record": {}})


def record_messages(records: Iterable[TransitionRecord], parameters: Sequence[ParameterRecord] = ()
                    ) -> list[tuple[str, dict]]:
    """The node pages' live audit rows for new transition records, and one word to the audit
    pages when transition or parameter records were stored: (group, message) pairs."""
    records = list(records)
    messages = [
        (protocol.node_group(record.node.key), {"type": "audit.record", "record": record.as_dict()})
        for record in records
        if record.node_id is not None and record.node is not None
    ]
    if records or parameters:
        messages.append(AUDIT_STORED)
    return messages


# Live updates sent side by side (fewer than the channel layer's Redis pool of 100 connections).
PUSH_CONCURRENCY = 50
# The server's event loop, set by lifecycle_site/http_handler.py for the requests it runs: their
# pushes are handed to it and go out while the answer goes back, instead of before it (under
# load a push waited ~100 ms for the loop, which serves every page's socket too).
server_loop: ContextVar[asyncio.AbstractEventLoop | None] = ContextVar("server_loop", default=None)
# Handed-over pushes not sent yet; beyond this many (Redis hanging), new ones are dropped and
# logged: what was stored is on every page the next time it loads.
MAX_PENDING = 500
_pending = 0
_pending_lock = threading.Lock()
# Outside the server (the ingest process), pushes go through one kept loop and are waited for,
# at most this long (Redis hanging): what was stored is on every page the next time it loads.
SEND_TIMEOUT_S = 5.0
_loop: asyncio.AbstractEventLoop | None = None
_loop_lock = threading.Lock()


def push(messages: list[tuple[str, dict]]) -> None:
    """Send (group, message) pairs to the Channels layer; a failure is logged, never raised
    (what was stored is there for the next page load). In a request of the server, returns at
    once and the server's event loop sends them; elsewhere (the ingest process) waits for them,
    sent from a loop of this process's own."""
    if not messages:
        return
    layer = get_channel_layer()
    if layer is None:
        return
    loop = server_loop.get()
    if loop is not None:
        _hand_over(loop, layer, messages)
        return
    future = asyncio.run_coroutine_threadsafe(_send_all(layer, messages), _own_loop())
    try:
        results = future.result(timeout=SEND_TIMEOUT_S)
    except TimeoutError:
        future.cancel()
        results = [TimeoutError(f"not sent within {SEND_TIMEOUT_S:g} s")]
    except Exception as exc:  # noqa: BLE001 - the channel layer's errors are many; none must stop us
        future.cancel()
        results = [exc]
    _report(results, len(messages))


def _own_loop() -> asyncio.AbstractEventLoop:
    """This process's event loop for pushes made outside the server, in a thread of its own and
    kept: the channel layer keeps a Redis connection pool per loop, so a loop per call (as
    ``async_to_sync`` makes) connected anew, and started a thread, for every push."""
    global _loop
    with _loop_lock:
        if _loop is None:  # never closed: it lives as long as the process
            _loop = asyncio.new_event_loop()
            threading.Thread(target=_loop.run_forever, name="live-updates", daemon=True).start()
        return _loop


async def _send_all(layer: Any, messages: list[tuple[str, dict]]) -> list:
    # A few at a time: the channel layer's Redis pool holds at most 100 connections, and a
    # group_send beyond them fails ("Too many connections"), losing its message.
    results: list = []
    for start in range(0, len(messages), PUSH_CONCURRENCY):
        chunk = messages[start : start + PUSH_CONCURRENCY]
        results += await asyncio.gather(*(layer.group_send(g, m) for g, m in chunk), return_exceptions=True)
    return results


def _hand_over(loop: asyncio.AbstractEventLoop, layer: Any, messages: list[tuple[str, dict]]) -> None:
    global _pending
    with _pending_lock:
        if _pending >= MAX_PENDING:
            log.warning("dropped %d live updates: %d are still waiting to be sent (is Redis answering?)",
                        len(messages), _pending)
            return
        _pending += 1

    def sent(future: Future) -> None:
        global _pending
        with _pending_lock:
            _pending -= 1
        try:
            results = future.result()
        except Exception as exc:  # noqa: BLE001
            results = [exc]
        _report(results, len(messages))

    try:
        asyncio.run_coroutine_threadsafe(_send_all(layer, messages), loop).add_done_callback(sent)
    except RuntimeError as exc:  # the loop is closed: the server is stopping
        with _pending_lock:
            _pending -= 1
        _report([exc], len(messages))


def pending() -> int:
    """Pushes handed to the server's loop and not sent yet."""
    return _pending


def _report(results: list, count: int) -> None:
    failures = [r for r in results if isinstance(r, Exception)]
    if failures:
        log.warning("could not push %d of %d live updates: %s", len(failures), count, failures[0])
