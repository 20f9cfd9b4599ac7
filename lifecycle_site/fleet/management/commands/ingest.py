"""``manage.py ingest``: the only writer of what gateways report.

One loop: read every gateway's facts and logs streams (a Redis consumer group), apply each
batch in one transaction that also records how far the stream was applied, acknowledge it,
then tell the pages. Between reads: copy the heartbeats into the Gateway rows, publish each
gateway's config, keep the gateways' Redis users in place and prune old log records.

Safe to run twice: one process at a time holds the ingest lease in Redis, the other stands
by and takes over within LEASE_S; entries up to a stream's recorded cursor are acknowledged
without being applied again (a crash between commit and acknowledgement), and audit records
are keyed by fact id.
"""
from __future__ import annotations

import logging
import os
import signal
import socket
import time
import uuid
from typing import Any

import redis
from django.conf import settings
from django.core.management.base import BaseCommand
from django.db import DatabaseError, InterfaceError, OperationalError, connection, transaction

from lifecycle_site.alerts.engine import Evaluator
from lifecycle_site.fleet import gateways as gw
from lifecycle_site.fleet import redis_users
from lifecycle_site.fleet.absences import prune_absences
from lifecycle_site.fleet.fact_context import FactRejected
from lifecycle_site.fleet.facts import apply_facts
from lifecycle_site.fleet.live_updates import push, record_messages
from lifecycle_site.fleet.log_store import LogTargets, prune_logs, store_batch
from lifecycle_site.fleet.models import Gateway
from lifecycle_site.fleet.runs import fail_runs_of_silent_gateways
from lifecycle_site.fleet.stream_entries import beat_fields, count_gap, decode, entry_id, is_after, replied, text
from ros_gateway.shared import protocol

log = logging.getLogger("lifecycle_site.ingest")

# Every ingest process reads as the same consumer: only the lease holder reads at all, and
# whoever holds it next finds the entries delivered but not acknowledged as its own.
CONSUMER = "site"
LEASE_S = 15.0
READ_COUNT = 500
BLOCK_MS = 1000
REFRESH_S = 3.0  # re-read the Gateway rows
BEATS_S = 2.0  # copy heartbeats and backlogs, check configs
CONFIG_EVERY_S = 60.0  # publish configs even when unchanged
USERS_S = 10.0  # check the gateways' Redis users
PRUNE_S = 60.0
COMPLAIN_EVERY_S = 30.0
# A gateway appends a request's facts to its stream (marked protocol.REPLIED) in one round trip
# with its reply, which carries the same facts to the site, which applies them at once. Reading
# them, ingest waits this long before applying them, so that the two do not write at the same
# moment: SQLite takes one writer at a time and the other sleeps in its busy handler (1, 2, 5,
# 10 ms ...), which the requester would wait for.
SETTLE_S = 0.03
# Facts no reply carries (a node's own transitions, discovery) wait less: this long after they
# were added, the live push of the same event has reached the pages; stored at once, they took
# the CPU from it on a small machine (push median 8 -> 10 ms on 2 cores, docs/performance.md).
SETTLE_OTHERS_S = 0.01

RENEW = "if redis.call('get', KEYS[1]) == ARGV[1] then return redis.call('pexpire', KEYS[1], ARGV[2]) end return 0"
RELEASE = "if redis.call('get', KEYS[1]) == ARGV[1] then return redis.call('del', KEYS[1]) end return 0"


class Ingest:
    """The loop's state; ``step()`` is one turn (tests drive it directly)."""

    def __init__(self, client: redis.Redis | None = None) -> None:
        self.redis = client or gw.redis_client()
        self.prefix = gw.channel_prefix()
        self.me = f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"
        self.lease_key = protocol.ingest_lease_key(self.prefix)
        self.stopping = False
        self.streams: dict[str, tuple[str, str]] = {}  # stream key -> (gateway, "facts" | "logs")
        self.ready: set[str] = set()  # streams whose consumer group exists
        self.catching_up: set[str] = set()  # streams whose delivered, unacknowledged entries come first
        self.published: dict[str, tuple[str, float]] = {}  # gateway -> (config version, when)
        self.due: dict[str, float] = {}
        self.last_complaint = 0.0
        self.applied = 0
        self.alerts = Evaluator()  # alert rules, evaluated here: once per site (docs/alerts.md)

    # --- the loop --------------------------------------------------------------------------

    def run(self) -> None:
        holding = False
        while not self.stopping:
            try:
                if not self.hold_lease():
                    if holding:
                        log.warning("lost the ingest lease; standing by")
                    holding = False
                    self.catching_up = set(self.streams)
                    time.sleep(1.0)
                    continue
                if not holding:
                    log.info("holding the ingest lease (%s)", self.me)
                    holding = True
                self.step()
            except redis.RedisError as exc:
                self.complain(f"Redis at {gw.safe_url(settings.REDIS_URL)} failed: {exc}; retrying")
                self.ready.clear()
                self.published.clear()  # a Redis restarted without its data has lost the configs
                time.sleep(1.0)
            except DatabaseError as exc:
                self.complain(f"the database failed: {exc}; retrying")
                connection.close()
                time.sleep(1.0)
        self.release_lease()
        self.alerts.dispatcher.stop()

    def step(self, block_ms: int = BLOCK_MS) -> int:
        """Read and apply what is there (waiting up to ``block_ms``), then the periodic work."""
        if self.is_due("refresh", REFRESH_S):
            self.refresh()
        applied = self.read(block_ms)
        self.alerts.tick()
        if self.is_due("beats", BEATS_S):
            self.copy_beats()
            self.publish_configs()
            fail_runs_of_silent_gateways()
        if self.is_due("users", USERS_S):
            self.keep_users()
        if self.is_due("prune", PRUNE_S):
            config = settings.LIFECYCLE
            deleted = prune_logs(config["LOG_KEEP_PER_NODE"], config["LOG_KEEP_HOURS"])
            if deleted:
                log.info("pruned %d old log records", deleted)
            prune_absences()
        return applied

    def is_due(self, what: str, every: float) -> bool:
        now = time.monotonic()
        if now < self.due.get(what, 0.0):
            return False
        self.due[what] = now + every
        return True

    def complain(self, text: str) -> None:
        now = time.monotonic()
        if now - self.last_complaint > COMPLAIN_EVERY_S:
            self.last_complaint = now
            log.warning(text)

    # --- the lease -------------------------------------------------------------------------

    def hold_lease(self) -> bool:
        ms = int(LEASE_S * 1000)
        if self.redis.set(self.lease_key, self.me, nx=True, px=ms):
            return True
        return bool(self.redis.eval(RENEW, 1, self.lease_key, self.me, ms))

    def release_lease(self) -> None:
        try:
            self.redis.eval(RELEASE, 1, self.lease_key, self.me)
        except redis.RedisError:
            pass

    # --- streams ---------------------------------------------------------------------------

    def refresh(self) -> None:
        """Follow the Gateway rows: a consumer group on the streams of each."""
        streams = {}
        for name in Gateway.objects.values_list("name", flat=True):
            streams[protocol.facts_stream(self.prefix, name)] = (name, "facts")
            streams[protocol.logs_stream(self.prefix, name)] = (name, "logs")
        for stream in streams:
            if stream not in self.ready:
                try:
                    self.redis.xgroup_create(stream, protocol.INGEST_GROUP, id="0", mkstream=True)
                except redis.ResponseError as exc:
                    if "BUSYGROUP" not in str(exc):
                        raise
                self.ready.add(stream)
                self.catching_up.add(stream)
        self.streams = streams
        self.ready &= set(streams)
        self.catching_up &= set(streams)

    def read(self, block_ms: int) -> int:
        """First the entries delivered earlier but never acknowledged, then new ones."""
        if not self.streams:
            time.sleep(block_ms / 1000)
            return 0
        try:
            if self.catching_up:
                replies = self.redis.xreadgroup(
                    protocol.INGEST_GROUP, CONSUMER, {s: "0" for s in self.catching_up}, count=READ_COUNT
                )
            else:
                replies = self.redis.xreadgroup(
                    protocol.INGEST_GROUP, CONSUMER, {s: ">" for s in self.streams}, count=READ_COUNT,
                    block=block_ms,
                )
        except redis.ResponseError as exc:
            if "NOGROUP" in str(exc):  # Redis restarted without its data
                self.ready.clear()
                self.published.clear()
                self.due.pop("refresh", None)
                return 0
            raise
        self.settle(replies or [])
        applied = 0
        for raw_stream, entries in replies or []:
            stream = text(raw_stream)
            if not entries:
                self.catching_up.discard(stream)
                continue
            if stream not in self.streams:
                continue
            try:
                applied += self.apply(stream, entries)
            except Exception:
                self.catching_up.add(stream)  # not acknowledged: read again
                raise
        self.applied += applied
        return applied

    def settle(self, replies: list) -> None:
        """Wait until every facts entry read is old enough (by its id, Redis's clock in ms;
        never longer than its settle time, whatever the clocks say): SETTLE_S for those a
        reply carried too (the site applies a reply's facts first), SETTLE_OTHERS_S for others."""
        now, wait = time.time(), 0.0
        for stream, entries in replies:
            if self.streams.get(text(stream), ("", ""))[1] != "facts":
                continue
            for entry, fields in entries:
                settle = SETTLE_S if replied(fields) else SETTLE_OTHERS_S
                age = now - entry_id(entry)[0] / 1000
                wait = max(wait, min(max(settle - age, 0.0), settle))
        if wait:
            time.sleep(wait)

    def apply(self, stream: str, entries: list) -> int:
        """Apply one stream's entries in one transaction, then acknowledge them."""
        name, kind = self.streams[stream]
        pushes: list[tuple[str, dict]] = []
        with transaction.atomic():
            row = Gateway.objects.select_for_update().filter(name=name).first()
            if row is None:
                return 0
            cursor = row.facts_cursor if kind == "facts" else row.logs_cursor
            fresh = [(entry, fields) for entry, fields in entries if is_after(entry, cursor)]
            if kind == "facts":
                pushes = self.apply_facts(row, fresh)
            else:
                pushes = self.store_logs(row, fresh)
            if fresh:
                setattr(row, f"{kind}_cursor", text(fresh[-1][0]))
            row.save(update_fields=[
                f"{kind}_cursor", f"{kind}_instance", f"{kind}_seq", "facts_lost", "facts_rejected",
                "logs_lost", "logs_dropped", "logs_received",
            ])
        self.redis.xack(stream, protocol.INGEST_GROUP, *[entry for entry, _ in entries])
        # Stored and acknowledged: Redis keeps only what is not (MAXLEN then bounds a backlog,
        # not a history), so a small Redis (Edge: 40 MB, noeviction) never fills up with it.
        if entries:
            self.redis.xtrim(stream, minid=text(entries[-1][0]))
        push(pushes)
        return len(fresh)

    def apply_facts(self, row: Gateway, entries: list) -> list[tuple[str, dict]]:
        facts = []
        for entry, fields in entries:
            try:
                fact = decode(fields)
            except FactRejected as exc:
                row.facts_rejected += 1
                log.warning("gateway %s: skipped facts entry %s: %s", row.name, entry, exc)
                continue
            lost, row.facts_instance, row.facts_seq = count_gap(
                fact.get("instance"), fact.get("seq"), row.facts_instance, row.facts_seq)
            if lost:
                row.facts_lost += lost
                log.warning("gateway %s: %d facts were trimmed from Redis before they could be stored "
                            "(the ingest process was behind or stopped)", row.name, lost)
            facts.append(fact)
        applied = apply_facts(row.name, facts)
        self.alerts.observe(row.name, facts)
        row.facts_rejected += applied.rejected
        return record_messages(applied.created, applied.created_parameters)

    def store_logs(self, row: Gateway, entries: list) -> list[tuple[str, dict]]:
        pushes: list[tuple[str, dict]] = []
        targets = LogTargets(row.name)
        for entry, fields in entries:
            try:
                batch = decode(fields)
                lost, row.logs_instance, row.logs_seq = count_gap(
                    batch.get("instance"), batch.get("seq"), row.logs_instance, row.logs_seq)
                if lost:
                    row.logs_lost += lost
                    log.warning("gateway %s: %d log batches were trimmed from Redis before they could be "
                                "stored", row.name, lost)
                row.logs_dropped += max(int(batch.get("dropped") or 0), 0)
                if batch.get("gateway") != row.name:
                    raise FactRejected(f"it names gateway {batch.get('gateway')!r}")
                with transaction.atomic():
                    pushes += store_batch(targets, batch)
                row.logs_received += len(batch.get("records") or [])
            except (OperationalError, InterfaceError):
                raise  # the database itself is unavailable: the whole batch is tried again
            except Exception as exc:  # noqa: BLE001 - a malformed batch must not block the stream
                row.logs_lost += 1
                log.warning("gateway %s: skipped log batch %s: %s", row.name, entry, exc)
        return pushes

    # --- what else the site owes its gateways ----------------------------------------------

    def copy_beats(self) -> None:
        """Each gateway's heartbeat and stream backlog into its row (for pages and the API)."""
        names = sorted({name for name, _ in self.streams.values()})
        if not names:
            return
        beats = self.redis.mget([protocol.beat_key(self.prefix, n) for n in names])
        backlogs = self.backlogs(names)
        for name, raw in zip(names, beats, strict=True):
            changes: dict[str, Any] = {"backlog": backlogs.get(name, 0)}
            beat = gw._parse_beat(raw)
            if beat is not None:
                changes.update(beat_fields(beat))
            Gateway.objects.filter(name=name).update(**changes)

    def backlogs(self, names: list[str]) -> dict[str, int]:
        """Entries not yet stored, per gateway: the group's lag (Redis 7) or an estimate, plus
        what was delivered and not acknowledged."""
        streams = [(n, s) for n in names for s in (protocol.facts_stream(self.prefix, n),
                                                   protocol.logs_stream(self.prefix, n))]
        pipe = self.redis.pipeline(transaction=False)
        for _, stream in streams:
            pipe.xinfo_groups(stream)
        totals: dict[str, int] = {}
        for (name, stream), groups in zip(streams, pipe.execute(raise_on_error=False), strict=True):
            if isinstance(groups, Exception):
                continue
            for group in groups:
                if group.get("name") not in (protocol.INGEST_GROUP, protocol.INGEST_GROUP.encode()):
                    continue
                lag = group.get("lag")
                if lag is None:
                    last = group.get("last-delivered-id") or b"0-0"
                    last = text(last)
                    lag = len(self.redis.xrange(stream, f"({last}", "+", count=10_000))
                totals[name] = totals.get(name, 0) + int(lag) + int(group.get("pending") or 0)
        return totals

    def publish_configs(self) -> None:
        """Each gateway's config when it changed, and at least every CONFIG_EVERY_S."""
        now = time.monotonic()
        for name in sorted({name for name, _ in self.streams.values()}):
            config = gw.build_config(name)
            version, when = self.published.get(name, ("", 0.0))
            if config["version"] != version or now - when >= CONFIG_EVERY_S:
                self.redis.set(protocol.config_key(self.prefix, name), protocol.encode(config))
                self.published[name] = (config["version"], now)

    def keep_users(self) -> None:
        """Re-create gateways' Redis users that Redis lost (a restart without persistence)."""
        for row in Gateway.objects.exclude(redis_password_sha256=""):
            if not redis_users.user_is_current(row, self.redis):
                redis_users.apply_user(row, self.redis)
                log.info("re-created the Redis user %s of gateway %s", row.redis_user, row.name)


class Command(BaseCommand):
    help = "Store what the gateways report (facts, logs, heartbeats) and keep their configs and Redis users."

    def handle(self, *args: Any, **options: Any) -> None:
        ingest = Ingest()

        def stop(signum: int, frame: Any) -> None:
            self.stdout.write(f"{signal.strsignal(signum)}: finishing the current batch ...")
            ingest.stopping = True

        signal.signal(signal.SIGTERM, stop)
        signal.signal(signal.SIGINT, stop)
        self.stdout.write(f"ingest is running ({ingest.me}, Redis {gw.safe_url(settings.REDIS_URL)}, "
                          f"prefix {ingest.prefix})")
        ingest.run()
        self.stdout.write(f"ingest stopped after storing {ingest.applied} entries.")
