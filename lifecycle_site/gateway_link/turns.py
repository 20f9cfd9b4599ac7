"""A thread of the ingest process that does one thing over and over (the live relay, the Redis
guard): Redis or the database failing is survived, said at most every COMPLAIN_EVERY_S."""
from __future__ import annotations

import logging
import threading
import time
from typing import Callable

import redis
from django.db import DatabaseError, connection

COMPLAIN_EVERY_S = 30.0


def keep_turning(turn: Callable[[], object], stopping: threading.Event, what: str, log: logging.Logger,
                 pause: float = 0.0, after_failure: float = 1.0) -> None:
    """Call ``turn`` until ``stopping`` is set, ``pause`` seconds apart (``after_failure`` after
    one that failed)."""
    complained = -COMPLAIN_EVERY_S
    while not stopping.is_set():
        try:
            turn()
        except Exception as exc:  # noqa: BLE001 - the thread must outlive any one turn
            if time.monotonic() - complained > COMPLAIN_EVERY_S:
                complained = time.monotonic()
                known = isinstance(exc, (redis.RedisError, DatabaseError))
                log.warning("%s failed: %s; trying again", what, exc, exc_info=not known)
            if isinstance(exc, DatabaseError):
                connection.close()
            stopping.wait(after_failure)
            continue
        if pause:
            stopping.wait(pause)
