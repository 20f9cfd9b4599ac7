"""Redis's memory, shared by the site and every gateway, kept from being filled by one gateway.

Redis has no per-user memory limit, and it refuses every write once it is full (maxmemory,
``noeviction``): commands to every gateway, the pages' sockets, the ingest process. So the site
counts what each gateway's keys hold (those it writes: its streams, heartbeat, lease, replies and
claims) and cuts off a gateway beyond its quota (gateway_link.gateway_config.redis_quota) before Redis is
full: its user disabled, its connections closed, its keys deleted (gateway_link/quarantine.py).

An honest gateway never gets there: it trims its own streams to shares of the quota
(ros_gateway/budget.py). The count runs in every ingest process: a cheap look at Redis's memory
every POLL_S, and a count of every gateway's keys every FULL_S or at once when memory grew by
more than half a quota. A gateway that writes faster than that (over a local link) may still fill
Redis for a moment; whoever then meets Redis's "OOM" refusal (the site sending a command) calls
``relieve()``, which counts at once, cuts off the culprit and lets the write be tried again.
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import redis
from django.db import DatabaseError

from lifecycle_site.fleet.models import Gateway
from lifecycle_site.gateway_link import gateway_config, gateways, quarantine
from lifecycle_site.gateway_link.turns import keep_turning
from ros_gateway.shared import protocol

log = logging.getLogger(__name__)

POLL_S = 0.1
FULL_S = 1.0
ROWS_EVERY_S = 5.0  # the rows' redis_bytes (what pages and /metrics show)
# Replies and claims a gateway may hold at once: each claim lives 180 s, so a gateway that takes
# 100 commands a second holds 18,000 (the count of keys bounds the guard's own scan).
MAX_KEYS = 50_000


@dataclass
class Usage:
    bytes: int = 0
    keys: int = 0


def is_out_of_memory(exc: Exception) -> bool:
    """Redis refused a write: it is full (``OOM command not allowed when used memory > 'maxmemory'``)."""
    return isinstance(exc, redis.exceptions.OutOfMemoryError) or (
        isinstance(exc, redis.ResponseError) and "maxmemory" in str(exc))


class RedisGuard:
    def __init__(self, client: redis.Redis | None = None) -> None:
        self.redis = client or gateways.redis_client()
        self.prefix = gateways.channel_prefix()
        self.counted_at = 0.0
        self.counted_memory = 0
        self.rows_at = 0.0
        self.usage: dict[str, Usage] = {}
        self._lock = threading.Lock()

    # --- counting ------------------------------------------------------------------------

    def measure(self) -> dict[str, Usage]:
        """Bytes (MEMORY USAGE) and number of the keys each gateway wrote."""
        head = f"{self.prefix}:gw:"
        keys: dict[str, list[bytes]] = {}
        for key in self.redis.scan_iter(match=f"{head}*", count=1000):
            # Every key of the gateway, the site's too (its queue, config, verdicts: small, and on
            # Redis 6 the gateway can write them).
            keys.setdefault(key.decode(errors="replace")[len(head):].partition(":")[0], []).append(key)
        usage: dict[str, Usage] = {}
        for name, found in keys.items():
            with self.redis.pipeline(transaction=False) as pipe:
                for key in found[:MAX_KEYS + 1]:
                    pipe.memory_usage(key, samples=0)  # every element: a sample of 5 missed 99 % of a list
                sizes = pipe.execute(raise_on_error=False)
            usage[name] = Usage(sum(s for s in sizes if isinstance(s, int)), len(found))
        return usage

    def check(self) -> list[str]:
        """Count, and cut off every gateway beyond its quota; returns their names."""
        with self._lock:  # the ingest's thread and a request's relieve() may come together
            quota = gateway_config.redis_quota(self.redis)
            self.usage = self.measure()
            self.counted_at = time.monotonic()
            self.counted_memory = self.used_memory()
            held = quarantine.current(self.redis)
            cut = []
            for name, usage in sorted(self.usage.items()):
                if usage.bytes <= quota and usage.keys <= MAX_KEYS:
                    continue
                if name in held:  # cut off before; whatever it left is deleted again
                    quarantine.drop_keys(name, protocol.GATEWAY_WRITES, self.redis)
                    continue
                too_many = f"{usage.keys:,} keys (at most {MAX_KEYS:,})" if usage.keys > MAX_KEYS else ""
                held_bytes = f"{usage.bytes / 1e6:.1f} MB (its quota: {quota / 1e6:.1f} MB)"
                reason = (f"its Redis keys held {too_many or held_bytes}; they were deleted so that Redis, "
                          "which the site and every gateway share, does not fill up")
                quarantine.quarantine(name, reason, self.redis, drop=protocol.GATEWAY_WRITES)
                cut.append(name)
            return cut

    def used_memory(self) -> int:
        return int(self.redis.info("memory").get("used_memory") or 0)

    # --- when to count -----------------------------------------------------------------------

    def turn(self) -> list[str]:
        """One look at Redis (every POLL_S): a full count when it is due or memory grew."""
        now = time.monotonic()
        grown = self.used_memory() - self.counted_memory
        if now - self.counted_at >= FULL_S or grown > gateway_config.redis_quota(self.redis) // 2:
            cut = self.check()
            if now - self.rows_at >= ROWS_EVERY_S:
                self.rows_at = now
                self.store_rows()
            return cut
        return []

    def store_rows(self) -> None:
        try:
            for row in Gateway.objects.only("name", "redis_bytes"):
                counted = self.usage.get(row.name, Usage()).bytes
                if counted != row.redis_bytes:
                    Gateway.objects.filter(pk=row.pk).update(redis_bytes=counted)
        except DatabaseError as exc:
            log.warning("could not store the gateways' Redis usage: %s", exc)

    def run(self, stopping: threading.Event) -> None:
        """The guard's own thread (in every ingest process)."""
        keep_turning(self.turn, stopping, "counting the gateways' Redis memory", log, pause=POLL_S,
                     after_failure=POLL_S)


_shared: RedisGuard | None = None
_shared_lock = threading.Lock()


def relieve() -> list[str]:
    """Redis refused a write for lack of memory: count now and cut off whoever is beyond their
    quota (what they hold is deleted). Returns their names: empty when no gateway is to blame."""
    global _shared
    with _shared_lock:
        if _shared is None:
            _shared = RedisGuard()
    try:
        return _shared.check()
    except redis.RedisError as exc:
        log.warning("could not relieve Redis's memory: %s", exc)
        return []
