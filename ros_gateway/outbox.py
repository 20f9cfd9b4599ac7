"""Facts on their way to the site: numbered, held in bounded memory, and appended to this
gateway's Redis streams (``XADD MAXLEN ~``) by one flusher task.

While Redis is unreachable the facts wait here, in order, and go out when it is back. Past
the bound the oldest are dropped and counted; the count travels in the heartbeat, and the
site shows it. Each fact carries this instance's id and a sequence number, so the site can
also count facts that Redis trimmed before they were read.
"""
from __future__ import annotations

import asyncio
import logging
from collections import deque
from datetime import datetime, timezone
from typing import Any

from ros_gateway.budget import StreamBudget
from ros_gateway.relay import Relay
from ros_gateway.shared import protocol

log = logging.getLogger(__name__)

FLUSH_BATCH = 500
RETRY_AFTER_S = 0.5


class _Stream:
    """One outgoing stream: its bounded queue, sequence and counters, and its share of the
    gateway's Redis quota (its MAXLEN with each XADD)."""

    def __init__(self, key: str, maxlen: int, limit: int, share: float, largest: int) -> None:
        self.key = key
        self.budget = StreamBudget(share, maxlen)
        self.largest = largest  # bytes; the site reads no larger entry
        self.queue: deque[dict] = deque()
        self.limit = limit
        self.seq = 0
        self.sent = 0
        self.dropped = 0

    def add(self, entry: dict) -> None:
        if len(self.queue) >= self.limit:
            self.queue.popleft()
            self.dropped += 1
        self.queue.append(entry)


class Outbox:
    def __init__(self, relay: Relay, gateway: str, instance: str) -> None:
        self.relay, self.gateway, self.instance = relay, gateway, instance
        self.facts = _Stream(relay.key("facts"), protocol.FACTS_MAXLEN, protocol.OUTBOX_FACTS_LIMIT,
                             protocol.STREAM_SHARES["facts"], protocol.MAX_FACT_BYTES)
        self.logs = _Stream(relay.key("logs"), protocol.LOGS_MAXLEN, protocol.OUTBOX_LOG_BATCHES_LIMIT,
                            protocol.STREAM_SHARES["logs"], protocol.MAX_LOG_BATCH_BYTES)
        self._wake = asyncio.Event()
        self._flushed = asyncio.Condition()
        self._sending = asyncio.Lock()  # one pipeline at a time: the streams stay in seq order
        self.unreachable_since: float | None = None
        self._seeded = False  # what the streams already hold is counted in their budgets

    def _envelope(self, stream: _Stream, kind: str | None) -> dict:
        stream.seq += 1
        envelope = {"id": protocol.new_id(), "gateway": self.gateway, "instance": self.instance, "seq": stream.seq,
                    "at": datetime.now(timezone.utc).isoformat()}
        if kind is not None:
            envelope["type"] = kind
        return envelope

    def emit(self, kind: str, **fields: Any) -> dict:
        """Queue one fact (returned as sent, envelope included); never blocks, never raises."""
        fact = {**self._envelope(self.facts, kind), **protocol.finite(fields)}
        self.facts.add(fact)
        self._wake.set()
        return fact

    def emit_fact(self, fact: dict) -> dict:
        """Queue a fact made elsewhere (protocol.not_carried_out) under this instance's envelope,
        keeping its id (so that the site records it once) and its time."""
        fields = {k: v for k, v in fact.items() if k not in ("type", "gateway", "instance", "seq")}
        return self.emit(fact["type"], **fields)

    def emit_logs(self, records: list[list], dropped: int = 0) -> None:
        """Queue one batch of log records (at most LOG_BATCH)."""
        self.logs.add({**self._envelope(self.logs, None), "dropped": dropped, "records": records})
        self._wake.set()

    async def delivered(self, fact: dict, timeout: float) -> bool:
        """Wait (bounded) until ``fact`` is in Redis; False if it is still waiting here."""
        seq = fact["seq"]

        def sent() -> bool:
            return self.facts.sent >= seq

        try:
            async with self._flushed:
                await asyncio.wait_for(self._flushed.wait_for(sent), timeout)
            return True
        except asyncio.TimeoutError:
            return False

    def set_quota(self, quota: int) -> None:
        """The site's quota for this gateway's Redis keys (bytes): the streams keep within it."""
        self.facts.budget.set_quota(quota)
        self.logs.budget.set_quota(quota)

    def counters(self) -> dict:
        return {"facts": len(self.facts.queue), "log_batches": len(self.logs.queue),
                "facts_dropped": self.facts.dropped, "logs_dropped": self.logs.dropped}

    async def run(self, stopping: asyncio.Event) -> None:
        """Send what is queued, as it comes; after a failure try again every RETRY_AFTER_S."""
        while not stopping.is_set():
            if not self.facts.queue and not self.logs.queue:
                self._wake.clear()
                try:
                    await asyncio.wait_for(self._wake.wait(), 1.0)
                except asyncio.TimeoutError:
                    continue
            if not await self.flush():
                await asyncio.sleep(RETRY_AFTER_S)

    async def flush(self) -> bool:
        """One round: facts first (they carry the audit), then log batches. False on failure."""
        for stream in (self.facts, self.logs):
            while stream.queue:
                try:
                    async with self._sending:
                        await self._seed()
                        batch = list(stream.queue)[:FLUSH_BATCH]
                        if not batch:
                            break
                        async with self.relay.redis.pipeline(transaction=False) as pipe:
                            self._add(pipe, stream, batch)
                            await pipe.execute()
                        await self._sent(stream, batch)
                except Exception as exc:
                    self._unreachable(f"sending {len(stream.queue)} facts to the site", exc)
                    return False
        return True

    async def reply(self, key: str, message: str, ttl: int) -> bool:
        """Hand a command's reply over together with every fact queued before it (its own
        among them), in one round trip and all or nothing (MULTI): whenever the reply exists,
        the stream holds its facts too (should the site die before storing them from the
        reply, its ingest process still finds them). False when Redis failed or too many facts
        wait: the caller then waits for the flusher and replies on its own."""
        async with self._sending:
            batch = list(self.facts.queue)
            if len(batch) > FLUSH_BATCH:
                return False
            try:
                await self._seed()
                async with self.relay.redis.pipeline(transaction=True) as pipe:
                    self._add(pipe, self.facts, batch, replied=True)
                    pipe.lpush(key, message)
                    pipe.expire(key, ttl)
                    await pipe.execute()
            except Exception as exc:
                self._unreachable("handing over a reply with its facts", exc)
                return False
            if batch:
                await self._sent(self.facts, batch)
        return True

    async def _seed(self) -> None:
        """Before the first XADD of this process: count what its streams hold (a predecessor's
        entries not read yet), so that the budgets' MAXLEN keeps them. Raises when Redis fails."""
        if self._seeded:
            return
        async with self.relay.redis.pipeline(transaction=False) as pipe:
            for stream in (self.facts, self.logs):
                pipe.xlen(stream.key)
                pipe.memory_usage(stream.key)
            found = await pipe.execute()
        for stream, entries, size in ((self.facts, found[0], found[1]), (self.logs, found[2], found[3])):
            stream.budget.seed(int(entries or 0), int(size or 0))
        self._seeded = True

    @staticmethod
    def _add(pipe: Any, stream: _Stream, batch: list[dict], replied: bool = False) -> None:
        for entry in batch:
            body = protocol.encode(entry)
            if len(body) > stream.largest:  # the site would not read it (and cut this gateway off)
                log.error("dropped an entry of %d bytes for %s (at most %d): %s", len(body), stream.key,
                          stream.largest, body[:200])
                stream.dropped += 1
                continue
            fields = {"f": body, **({protocol.REPLIED: "1"} if replied else {})}
            pipe.xadd(stream.key, fields, maxlen=stream.budget.add(len(body)), approximate=False)

    def _unreachable(self, what: str, exc: Exception) -> None:
        if self.unreachable_since is None:
            self.unreachable_since = asyncio.get_running_loop().time()
        self.relay.complain(what, exc)

    async def _sent(self, stream: _Stream, batch: list[dict]) -> None:
        if self.unreachable_since is not None:
            log.info("Redis is back: sending the %d facts and %d log batches held meanwhile",
                     len(self.facts.queue), len(self.logs.queue))
            self.unreachable_since = None
        # Entries dropped meanwhile (bound reached) were the oldest: drop only what was sent.
        sent_last = batch[-1]["seq"]
        while stream.queue and stream.queue[0]["seq"] <= sent_last:
            stream.queue.popleft()
        stream.sent = max(stream.sent, sent_last)
        if stream is self.facts:
            async with self._flushed:
                self._flushed.notify_all()
