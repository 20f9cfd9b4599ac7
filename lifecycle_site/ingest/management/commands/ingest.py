"""``manage.py ingest``: the only writer of what gateways report.

One loop: read the facts and logs streams of the gateways this process holds (a Redis consumer
group), apply each batch in short transactions that also record how far the stream was
applied, acknowledge it, then tell the pages. Beside it, two threads: the live relay (the
gateways' live updates, checked, to the pages; ingest/live_relay.py) and the Redis guard (no
gateway fills Redis; gateway_link/redis_guard.py).

Several may run side by side: each gateway's streams are read by one process at a time, the
gateways shared among them, and one of them does the site-wide work (ingest/shares.py).
Entries up to a stream's recorded cursor are acknowledged without being applied again (a crash
between commit and acknowledgement), and audit records are keyed by fact id.

A gateway whose streams break the rules (a key of another type, an entry malformed or too
large) is quarantined (gateway_link/quarantine.py) and the others go on.
"""
from __future__ import annotations

import logging
import os
import signal
import socket
import threading
import time
import uuid
from typing import Any

import redis
from django.conf import settings
from django.core.management.base import BaseCommand
from django.db import DatabaseError, InterfaceError, OperationalError, connection, transaction
from django.utils import timezone

from lifecycle_site.fleet.models import Gateway
from lifecycle_site.gateway_link import gateways as gw
from lifecycle_site.gateway_link import quarantine
from lifecycle_site.gateway_link.gateway_input import FactRejected
from lifecycle_site.gateway_link.redis_guard import RedisGuard
from lifecycle_site.gateway_link.stream_entries import count_gap, decode, entry_id, is_after, replied, text
from lifecycle_site.ingest import diagnostic_facts, state_chain, watchers
from lifecycle_site.ingest.absences import prune_absences
from lifecycle_site.ingest.duties import SiteDuties
from lifecycle_site.ingest.facts import apply_facts
from lifecycle_site.ingest.live_relay import LiveRelay
from lifecycle_site.ingest.live_updates import push, record_messages
from lifecycle_site.ingest.log_store import LogTargets, prune_logs, store_batch
from lifecycle_site.ingest.observations import observations
from lifecycle_site.ingest.outages import prune_outages
from lifecycle_site.ingest.run_orphans import fail_runs_of_silent_gateways
from lifecycle_site.ingest.shares import Shares
from lifecycle_site.ingest.stream_reader import StreamReader
from lifecycle_site.ingest.transactions import MAX_YIELD_S, YIELD_SHARE, transactions
from ros_gateway.shared import protocol

log = logging.getLogger("lifecycle_site.ingest")

# Every ingest process reads as the same consumer: a gateway's streams are read by one process
# at a time (its lease), and whoever holds them next finds the entries delivered but not
# acknowledged as its own.
CONSUMER = "site"
READ_COUNT = 500
BLOCK_MS = 1000
REFRESH_S = 3.0  # re-read the Gateway rows, renew and share the leases
BEATS_S = 2.0  # copy heartbeats and backlogs, check configs
USERS_S = 10.0  # check the gateways' Redis users
PRUNE_S = 60.0
TURN_S = 1.0  # how often this process says it is alive and turning (/readyz)
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


class Ingest:
    """The loop's state; ``step()`` is one turn (tests drive it directly)."""

    def __init__(self, client: redis.Redis | None = None) -> None:
        self.redis = client or gw.redis_client()
        self.prefix = gw.channel_prefix()
        self.me = f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"
        self.stopping = False
        self.shares = Shares(self.redis, self.prefix, self.me)
        self.duties = SiteDuties(self.redis, self.prefix)
        self.reader = StreamReader(self.redis, protocol.INGEST_GROUP, CONSUMER, self.quarantine)
        self.gateways: list[str] = []  # every gateway not quarantined (the site's work is for all)
        self.streams: dict[str, tuple[str, str]] = {}  # stream key -> (gateway, "facts" | "logs"), held
        self.catching_up: set[str] = set()  # streams whose delivered, unacknowledged entries come first
        self.due: dict[str, float] = {}
        self.last_complaint = 0.0
        self.applied = 0
        # The alert rules (registered by alerts/apps.py), evaluated by the leader: once per site.
        self.watchers = watchers.start()
        self.refresh_wanted = threading.Event()  # another thread quarantined a gateway

    # --- the loop --------------------------------------------------------------------------

    def run(self) -> None:
        stopping = threading.Event()
        relay_client = gw.redis_client()
        threads = [
            threading.Thread(target=LiveRelay(relay_client, self.prefix, lambda: set(self.held()),
                                              self.quarantine_elsewhere(relay_client)).run, args=(stopping,),
                             name="live-relay", daemon=True),
            threading.Thread(target=RedisGuard(gw.redis_client()).run, args=(stopping,), name="redis-guard",
                             daemon=True),
        ]
        for thread in threads:
            thread.start()
        try:
            while not self.stopping:
                try:
                    self.step()
                except redis.RedisError as exc:
                    self.complain(f"Redis at {gw.safe_url(settings.REDIS_URL)} failed: {exc}; retrying")
                    self.reader.ready.clear()
                    self.duties.forget()  # a Redis restarted without its data has lost the configs
                    self.due.pop("refresh", None)
                    time.sleep(1.0)
                except DatabaseError as exc:
                    self.complain(f"the database failed: {exc}; retrying")
                    connection.close()
                    time.sleep(1.0)
        finally:
            stopping.set()
            try:
                self.shares.leave()
            except redis.RedisError:
                pass
            for watcher in self.watchers:
                watcher.stop()

    def step(self, block_ms: int = BLOCK_MS) -> int:
        """Read and apply what is there (waiting up to ``block_ms``), then the periodic work."""
        if self.is_due("refresh", REFRESH_S) or self.refresh_wanted.is_set():
            self.refresh_wanted.clear()
            self.refresh()
        applied = self.read(block_ms)
        if self.shares.leader:
            handed = self.shares.take_over()
            for watcher in self.watchers:
                watcher.take(handed)
                watcher.tick()
            if self.is_due("beats", BEATS_S):
                self.duties.copy_beats(self.gateways)
                self.duties.publish_configs(self.gateways)
                fail_runs_of_silent_gateways()
                push(record_messages(state_chain.settle()))
                push(diagnostic_facts.mark_silent(timezone.now()))
            if self.is_due("users", USERS_S):
                self.duties.keep_users()
            if self.is_due("prune", PRUNE_S):
                config = settings.LIFECYCLE
                deleted = prune_logs(config["LOG_KEEP_PER_NODE"], config["LOG_KEEP_HOURS"])
                if deleted:
                    log.info("pruned %d old log records", deleted)
                prune_absences()
                prune_outages()
        if self.is_due("turn", TURN_S):
            self.shares.report_turn({"pid": os.getpid(), "host": socket.gethostname(),
                                     "gateways": sorted(self.held()), "leader": self.shares.leader})
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

    # --- leases and shares ------------------------------------------------------------------

    def hold_lease(self) -> bool:
        """The site-wide lease (alert rules, configs, users); the gateways are shared anyway."""
        return self.shares.hold_site_lease()

    def release_lease(self) -> None:
        try:
            self.shares.leave()
        except redis.RedisError:
            pass

    def held(self) -> set[str]:
        return {name for name, _ in self.streams.values()}

    def refresh(self) -> None:
        """Follow the Gateway rows and the quarantines; take this process's share of the
        gateways; a consumer group on the streams of each."""
        was_leader = self.shares.leader
        if self.hold_lease() != was_leader:
            if self.shares.leader:
                log.info("holding the ingest lease (%s): this process does the site-wide work", self.me)
            else:
                log.warning("lost the ingest lease; another process does the site-wide work")
        held_back = quarantine.current(self.redis)
        rows = Gateway.objects.filter(quarantined__isnull=True).values_list("name", flat=True)
        self.gateways = sorted(name for name in rows if name not in held_back)
        members = self.shares.report_turn({"pid": os.getpid(), "gateways": sorted(self.held())})
        mine = self.shares.rebalance(self.gateways, members)
        streams = {}
        for name in mine:
            streams[protocol.facts_stream(self.prefix, name)] = (name, "facts")
            streams[protocol.logs_stream(self.prefix, name)] = (name, "logs")
        self.reader.ready &= set(streams)  # (a gateway let back in reads from where it stopped)
        self.catching_up |= self.reader.prepare(streams)  # new to this process: what is pending first
        self.streams = {s: owner for s, owner in streams.items() if s in self.reader.ready}
        self.catching_up &= set(self.streams)

    def quarantine(self, gateway: str, reason: str, drop: list[str]) -> None:
        """Cut a gateway off and stop reading it (the others go on)."""
        quarantine.quarantine(gateway, reason, self.redis, drop=drop)
        self.streams = {s: owner for s, owner in self.streams.items() if owner[0] != gateway}
        self.gateways = [name for name in self.gateways if name != gateway]
        self.catching_up &= set(self.streams)
        self.reader.ready &= set(self.streams)

    def quarantine_elsewhere(self, client: redis.Redis):
        """The same for another thread (the live relay): the loop's own state is left to the
        loop, which follows at its next turn."""
        def cut_off(gateway: str, reason: str, drop: list[str]) -> None:
            quarantine.quarantine(gateway, reason, client, drop=drop)
            self.refresh_wanted.set()
        return cut_off

    # --- streams ---------------------------------------------------------------------------

    def read(self, block_ms: int) -> int:
        """First the entries delivered earlier but never acknowledged, then new ones."""
        if not self.streams:
            time.sleep(block_ms / 1000)
            return 0
        if self.catching_up:
            replies = self.reader.read(self.streams, {s: "0" for s in self.catching_up}, READ_COUNT, None)
            replies += [(s, []) for s in self.catching_up if s not in {r[0] for r in replies}]
        else:
            replies = self.reader.read(self.streams, {s: ">" for s in self.streams}, READ_COUNT, block_ms)
        if not self.reader.ready >= set(self.streams):  # a stream was found broken or without its group
            self.due.pop("refresh", None)
        self.settle(replies)
        applied = 0
        for stream, entries in replies:
            if not entries:
                self.catching_up.discard(stream)
                continue
            if stream not in self.streams:
                continue
            try:
                applied += self.apply(stream, entries)
            except (redis.RedisError, DatabaseError):
                self.catching_up.add(stream)  # not acknowledged: read again
                raise
            except Exception as exc:  # noqa: BLE001 - what one gateway sent must not stop the others
                gateway, kind = self.streams[stream]
                log.exception("gateway %s: its %s could not be applied", gateway, kind)
                self.quarantine(gateway, f"an entry of its {kind} stream could not be applied "
                                f"({type(exc).__name__}: {str(exc)[:200]})", [])
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
        """Apply one stream's entries in short transactions, then acknowledge them."""
        name, kind = self.streams[stream]
        applied = 0
        for chunk in transactions(kind, entries):
            began = time.monotonic()
            pushes: list[tuple[str, dict]] = []
            with transaction.atomic():
                row = Gateway.objects.select_for_update().filter(name=name).first()
                if row is None:
                    return applied
                cursor = row.facts_cursor if kind == "facts" else row.logs_cursor
                fresh = [(entry, fields) for entry, fields in chunk if is_after(entry, cursor)]
                pushes += self.apply_facts(row, fresh) if kind == "facts" else self.store_logs(row, fresh)
                if fresh:
                    setattr(row, f"{kind}_cursor", text(fresh[-1][0]))
                row.save(update_fields=[
                    f"{kind}_cursor", f"{kind}_instance", f"{kind}_seq", "facts_lost", "facts_rejected",
                    "logs_lost", "logs_dropped", "logs_received",
                ])
            applied += len(fresh)
            took = time.monotonic() - began
            if took > 1.0:
                log.warning("gateway %s: a %s transaction took %.1f s", name, kind, took)
            push(pushes)  # stored: the pages get it now, not after the pause below
            if connection.vendor == "sqlite":
                # SQLite serves waiting writers by polling (up to every 100 ms), not in turn: one
                # that begins again at once keeps the site's writes waiting for seconds while it
                # catches up. A pause after each transaction lets them in.
                time.sleep(min(took * YIELD_SHARE, MAX_YIELD_S))
        self.redis.xack(stream, protocol.INGEST_GROUP, *[entry for entry, _ in entries])
        # Stored and acknowledged: Redis keeps only what is not (MAXLEN then bounds a backlog,
        # not a history), so a small Redis (Edge: 40 MB, noeviction) never fills up with it.
        self.redis.xtrim(stream, minid=text(entries[-1][0]))
        return applied

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
        seen = observations(row.name, applied.accepted)
        if self.shares.leader:
            for watcher in self.watchers:
                watcher.take(seen)
        else:
            self.shares.hand_over(seen)
        row.facts_rejected += applied.rejected
        return record_messages(applied.created, applied.created_parameters) + applied.pushes

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
                dropped = batch.get("dropped")
                row.logs_dropped += min(max(dropped, 0), 10**9) if isinstance(dropped, int) else 0
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

    # --- kept for callers that use the loop's parts (tests) ----------------------------------

    def copy_beats(self) -> None:
        self.duties.copy_beats(self.gateways)


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
