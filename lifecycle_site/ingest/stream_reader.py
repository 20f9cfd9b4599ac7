"""Reading gateways' streams so that one gateway's broken stream cannot stop the others.

All streams this process holds are read in one XREADGROUP while all is well (one round trip,
blocking until something arrives). That command fails as a whole when one key is not a stream
(WRONGTYPE) or lacks the consumer group (NOGROUP: Redis restarted without its data, or the
gateway deleted its own stream; UNBLOCKED: it was deleted while the read waited). Then each
stream is looked at on its own: a missing group is made again; a key of another type is its
gateway's doing, and the gateway is quarantined (its key deleted, so that the stream works
again once the quarantine is lifted). Entries too large or without the payload field are the
same: their gateway is quarantined; such an entry is acknowledged and never applied.
"""
from __future__ import annotations

import logging
import time
from collections import deque
from typing import Callable

import redis

from lifecycle_site.gateway_link.stream_entries import text
from ros_gateway.shared import protocol

log = logging.getLogger(__name__)

# Largest payload per kind of stream; what each entry must carry.
LARGEST = {"facts": protocol.MAX_FACT_BYTES, "logs": protocol.MAX_LOG_BATCH_BYTES, "live": protocol.MAX_LIVE_BYTES}
FIELD = {"facts": b"f", "logs": b"f", "live": b"m"}

Quarantine = Callable[[str, str, list[str]], None]  # gateway, reason, keys to drop
# A gateway whose stream loses its group this often, this fast, is deleting it on purpose.
LOST_GROUPS, LOST_GROUPS_WITHIN_S = 10, 60.0
COMPLAIN_EVERY_S = 30.0


class StreamReader:
    def __init__(self, client: redis.Redis, group: str, consumer: str, quarantine: Quarantine) -> None:
        self.redis, self.group, self.consumer, self.quarantine = client, group, consumer, quarantine
        self.ready: set[str] = set()  # streams known to have the group
        self.lost_groups: dict[str, deque[float]] = {}  # gateway -> when its streams lost their group
        self.complained = -COMPLAIN_EVERY_S

    def prepare(self, streams: dict[str, tuple[str, str]], start: str = "0") -> set[str]:
        """Make the consumer group of each stream not known to have it; returns the streams that
        now have it (a gateway whose key is not a stream is quarantined)."""
        fresh = set()
        for stream, (gateway, kind) in streams.items():
            if stream in self.ready:
                continue
            try:
                self.redis.xgroup_create(stream, self.group, id=start, mkstream=True)
            except redis.ResponseError as exc:
                if "BUSYGROUP" in str(exc):
                    pass
                elif "WRONGTYPE" in str(exc):
                    self.quarantine(gateway, self.wrong_type(stream, kind), [kind])
                    continue
                else:
                    raise
            self.ready.add(stream)
            fresh.add(stream)
        return fresh

    def wrong_type(self, stream: str, kind: str) -> str:
        try:
            found = text(self.redis.type(stream))
        except redis.RedisError:
            found = "another type"
        return f"its {kind} stream in Redis was replaced by a {found} (deleted by the site)"

    def read(self, streams: dict[str, tuple[str, str]], ids: dict[str, str], count: int,
             block_ms: int | None) -> list[tuple[str, list]]:
        """XREADGROUP over ``ids`` (stream -> "0" or ">"); on a stream-level error, each stream
        is checked on its own and the read is left for the next turn."""
        if not ids:
            return []
        try:
            replies = self.redis.xreadgroup(self.group, self.consumer, ids, count=count, block=block_ms)
        except redis.ResponseError as exc:
            # UNBLOCKED: a stream read with BLOCK was deleted meanwhile (by its gateway).
            if not any(code in str(exc) for code in ("WRONGTYPE", "NOGROUP", "UNBLOCKED")):
                raise
            self.check(streams, list(ids))
            return []
        checked = []
        for raw_stream, entries in replies or []:
            stream = text(raw_stream)
            if stream in streams:
                checked.append((stream, self.well_formed(stream, streams[stream], entries)))
        return checked

    def check(self, streams: dict[str, tuple[str, str]], which: list[str]) -> None:
        """Find what broke a read: streams of another type quarantine their gateway, missing
        groups are made again."""
        with self.redis.pipeline(transaction=False) as pipe:
            for stream in which:
                pipe.type(stream)
            types = [text(t) for t in pipe.execute()]
        now = time.monotonic()
        for stream, found in zip(which, types, strict=True):
            gateway, kind = streams[stream]
            self.ready.discard(stream)  # made again by prepare(), from its start
            if found not in ("stream", "none"):
                self.quarantine(gateway, self.wrong_type(stream, kind), [kind])
                continue
            missing = found == "none" or not self.has_group(stream)
            if missing:  # deleted (by its gateway: the site never deletes a stream it reads)
                times = self.lost_groups.setdefault(gateway, deque(maxlen=LOST_GROUPS))
                times.append(now)
                if len(times) == LOST_GROUPS and now - times[0] < LOST_GROUPS_WITHIN_S:
                    self.quarantine(gateway, f"its {kind} stream was deleted {LOST_GROUPS} times within "
                                    f"{LOST_GROUPS_WITHIN_S:.0f} s (each time every read of it failed)", [])
        if now - self.complained > COMPLAIN_EVERY_S:
            self.complained = now
            log.warning("a read of the gateways' streams failed; checked %d of them one by one", len(which))

    def has_group(self, stream: str) -> bool:
        try:
            return any(text(g.get("name", b"")) == self.group for g in self.redis.xinfo_groups(stream))
        except redis.ResponseError:
            return False

    def well_formed(self, stream: str, owner: tuple[str, str], entries: list) -> list:
        """The entries of a stream that carry their payload within its size, up to the first
        other one: that one is acknowledged (never applied) and its gateway quarantined; those
        after it stay pending, read once the quarantine is lifted."""
        gateway, kind = owner
        field, largest = FIELD[kind], LARGEST[kind]
        # An entry delivered before and trimmed since (the gateway's MAXLEN, while it waited to
        # be acknowledged) comes back without fields: nothing to apply, nobody's fault (its gap
        # in the gateway's sequence numbers counts it as lost).
        trimmed = [entry for entry, fields in entries if not fields]
        if trimmed:
            self.redis.xack(stream, self.group, *trimmed)
            entries = [(entry, fields) for entry, fields in entries if fields]
        for position, (entry, fields) in enumerate(entries):
            payload = fields.get(field, fields.get(field.decode())) if isinstance(fields, dict) else None
            problem = ""
            if not isinstance(payload, (bytes, str)):
                problem = f"an entry of its {kind} stream ({text(entry)}) has no '{field.decode()}' field"
            elif len(payload) > largest:
                problem = (f"an entry of its {kind} stream ({text(entry)}) holds {len(payload):,} bytes, "
                           f"more than the {largest:,} the site reads")
            if problem:
                self.quarantine(gateway, problem, [])
                self.redis.xack(stream, self.group, entry)
                return entries[:position]
        return entries
