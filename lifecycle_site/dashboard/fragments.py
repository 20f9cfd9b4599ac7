"""Live fragments rendered once per process for all the sockets that get the same update.

A node's state change goes to every open fleet page and to each of its node pages, and every
socket used to render the same row or panel itself: 0.75 ms a fleet row, so at 10
transitions/s with 25 fleet pages open, about a third of a core of daphne's event loop, on
which every other push waits. Sockets that would render the same thing (the same template,
data, role, URL prefix and language) now share one rendering for a moment.
"""
from __future__ import annotations

import json
import threading
import time
from collections import OrderedDict
from typing import Callable

from django.utils import translation

KEEP_S = 1.0  # short: a panel carries the time it was rendered (how long a transition runs)
SIZE = 512

_kept: OrderedDict[str, tuple[float, str]] = OrderedDict()
_lock = threading.Lock()


def rendered(key_parts: tuple, render: Callable[[], str]) -> str:
    """``render()``'s result, shared with whoever asked with the same ``key_parts`` (anything
    JSON can write) within the last KEEP_S seconds."""
    key = json.dumps((translation.get_language(), key_parts), sort_keys=True, default=str)  # one per language
    now = time.monotonic()
    with _lock:
        kept = _kept.get(key)
        if kept is not None and now - kept[0] < KEEP_S:
            return kept[1]
    html = render()
    with _lock:
        _kept[key] = (now, html)
        _kept.move_to_end(key)
        while len(_kept) > SIZE:
            _kept.popitem(last=False)
    return html


def forget() -> None:
    with _lock:
        _kept.clear()
