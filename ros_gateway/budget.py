"""How much of its Redis quota a gateway's streams may hold, as the MAXLEN to send with each XADD.

The site counts the bytes of every gateway's keys and cuts off one over its quota (the quota is
in the gateway's config, ``limits.redis_bytes``). An honest gateway never gets there: it keeps
each stream's newest entries within a share of the quota (protocol.STREAM_SHARES), even when the
site's ingest process is stopped and nothing is read. The site trims what it has stored, so the
streams usually hold far less.
"""
from __future__ import annotations

from collections import deque

from ros_gateway.shared import protocol


class StreamBudget:
    """The sizes of a stream's newest entries whose sum stays within ``share`` of the quota."""

    def __init__(self, share: float, cap: int, quota: int = protocol.START_REDIS_QUOTA) -> None:
        self.share, self.cap = share, cap
        self.budget = int(quota * share)
        self.sizes: deque[int] = deque()
        self.total = 0

    def set_quota(self, quota: int) -> None:
        self.budget = int(quota * self.share)

    def seed(self, entries: int, size: int) -> None:
        """The stream already holds ``entries`` taking ``size`` bytes (written by this gateway's
        previous process, not read by the site yet): counted as the oldest, so that the next
        MAXLEN keeps them while they fit (a fresh count would be 1, and trim them all)."""
        entries = min(max(entries, 0), self.cap)
        if not entries:
            return
        each = max(size // entries, protocol.STREAM_ENTRY_OVERHEAD)
        self.sizes.extendleft([each] * entries)
        self.total += each * entries

    def add(self, size: int) -> int:
        """Count one entry of ``size`` bytes; returns how many of the newest entries the stream
        may keep (its exact MAXLEN), at least this one."""
        size += protocol.STREAM_ENTRY_OVERHEAD
        self.sizes.append(size)
        self.total += size
        while len(self.sizes) > 1 and (self.total > self.budget or len(self.sizes) > self.cap):
            self.total -= self.sizes.popleft()
        return len(self.sizes)


def quota_of(config: dict) -> int | None:
    """The quota the site gives this gateway (bytes), or None when its config names none."""
    limits = config.get("limits")
    quota = limits.get("redis_bytes") if isinstance(limits, dict) else None
    if isinstance(quota, int) and not isinstance(quota, bool) and quota > 0:
        return quota
    return None
