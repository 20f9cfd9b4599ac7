"""Whether a gateway's process still exists, seen from Redis's list of clients.

A gateway names its Redis connections (protocol.client_name) and says so in its beat. A
process that ends, killed included, closes them at once, so the site knows it is gone long
before its heartbeat grows old. A name counts as missing only from a list of clients read
after the site read what that process wrote (its beat, its claim of a command: written
through such a connection), and only from a list that shows the site's own connection: a
Redis the site may not list clients of (its ACL), or a proxy that hides them, makes no
gateway look gone.
"""
from __future__ import annotations

import os
import threading
import time

import redis

_clients: dict[str, tuple[float, frozenset[str] | None]] = {}  # "" -> (read at, connected names)
_lock = threading.Lock()
# How long a list of clients is trusted (as a heartbeat read: gateway_link.gateways.BEAT_CACHE_S).
CLIENTS_CACHE_S = 1.0
# The name of this process's connections: seeing it in CLIENT LIST shows that the list is
# Redis's own (not a proxy's), so a gateway's name missing from it means something.
SITE_CLIENT = f"lcm-site:{os.getpid()}"


def forget() -> None:
    with _lock:
        _clients.clear()


def connected_clients(client: redis.Redis, not_before: float = 0.0) -> tuple[float, frozenset[str] | None]:
    """When (monotonic, just before asking) and which connection names Redis listed, or None
    for the names when it cannot be asked; read again when older than CLIENTS_CACHE_S or than
    ``not_before``."""
    now = time.monotonic()
    with _lock:
        cached = _clients.get("")
    if cached is not None and cached[0] >= not_before and 0 <= now - cached[0] < CLIENTS_CACHE_S:
        return cached
    try:
        names: frozenset[str] | None = frozenset(
            c.get("name") or "" for c in client.client_list(_type="normal")) - {""}
    except redis.RedisError:
        names = None
    if names is not None and SITE_CLIENT not in names:
        names = None  # not Redis's own list
    with _lock:
        _clients[""] = (now, names)
    return now, names


def process_gone(redis_client: redis.Redis, client: str, written_before: float) -> bool:
    """Whether the gateway process whose connections bear the name ``client`` has ended, given
    that it wrote something the site read by ``written_before`` (monotonic)."""
    if not client:
        return False
    _, names = connected_clients(redis_client, not_before=written_before)
    return names is not None and client not in names
