"""Telling open pages what was stored: the live updates sent through the Channels layer after
facts are applied (by the ingest process and by the request path)."""
from __future__ import annotations

import asyncio
import logging
from typing import Iterable

from asgiref.sync import async_to_sync
from channels.layers import get_channel_layer

from lifecycle_site.audit.models import TransitionRecord
from ros_gateway.shared import protocol

log = logging.getLogger(__name__)

def record_messages(records: Iterable[TransitionRecord]) -> list[tuple[str, dict]]:
    """The node pages' live audit rows for new records: (group, message) pairs."""
    return [
        (protocol.node_group(record.node.key), {"type": "audit.record", "record": record.as_dict()})
        for record in records
        if record.node_id is not None and record.node is not None
    ]


# Live updates sent side by side (fewer than the channel layer's Redis pool of 100 connections).
PUSH_CONCURRENCY = 50


def push(messages: list[tuple[str, dict]]) -> None:
    """Send (group, message) pairs to the Channels layer; a failure is logged, never raised
    (what was stored is there for the next page load)."""
    if not messages:
        return
    layer = get_channel_layer()
    if layer is None:
        return

    async def send_all() -> list:
        # A few at a time: the channel layer's Redis pool holds at most 100 connections, and a
        # group_send beyond them fails ("Too many connections"), losing its message.
        results: list = []
        for start in range(0, len(messages), PUSH_CONCURRENCY):
            chunk = messages[start : start + PUSH_CONCURRENCY]
            results += await asyncio.gather(*(layer.group_send(g, m) for g, m in chunk), return_exceptions=True)
        return results

    try:
        failures = [r for r in async_to_sync(send_all)() if isinstance(r, Exception)]
    except Exception as exc:  # noqa: BLE001 - the channel layer's errors are many; none must stop us
        failures = [exc]
    if failures:
        log.warning("could not push %d of %d live updates: %s", len(failures), len(messages), failures[0])
