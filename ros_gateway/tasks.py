"""Background tasks of the gateway: kept referenced until done, their failures logged."""
from __future__ import annotations

import asyncio
import logging
from typing import Coroutine

log = logging.getLogger(__name__)

_running: set[asyncio.Future] = set()


def spawn(coroutine: Coroutine) -> asyncio.Future:
    """Run a coroutine in the background on the running loop."""
    task = asyncio.ensure_future(coroutine)
    _running.add(task)
    task.add_done_callback(_done)
    return task


def _done(task: asyncio.Future) -> None:
    _running.discard(task)
    if not task.cancelled() and task.exception() is not None:
        log.error("background task failed", exc_info=task.exception())


async def cancel_all() -> None:
    """Stop what is still running (the gateway is stopping)."""
    tasks = list(_running)
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
