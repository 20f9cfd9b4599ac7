"""Gateways' live updates, checked, to the pages that show what they are about.

A gateway cannot reach the Channels layer (its Redis user has no key of it): it appends its
live updates (``node.state``, ``node.parameters``, ``run.progress``) to its own ``live``
stream. Here, in a thread of each ingest process, the streams of the gateways this process
holds are read as they come (one blocking XREAD), each update is rebuilt from checked fields
(gateway_link/gateway_input.py: its robot exactly one of the gateway's own, a valid node name, a known
state, bounded sizes) and sent to the groups the site works out itself (the node's, its robot's,
the fleet's). What fails the checks is dropped and counted (the gateway's ``live_refused``); a
stream that is not a stream, or an entry without its payload or too large, quarantines its
gateway. A stream holds only what is not read yet: what is read is trimmed.
"""
from __future__ import annotations

import asyncio
import json
import logging
import threading
import time
from typing import Any, Callable

import redis
from channels.layers import get_channel_layer
from django.db.models import F

from lifecycle_site.fleet.models import Gateway, Robot
from lifecycle_site.gateway_link import gateway_input as checks
from lifecycle_site.gateway_link.stream_entries import text
from lifecycle_site.gateway_link.turns import keep_turning
from ros_gateway.shared import protocol

log = logging.getLogger(__name__)

BLOCK_MS = 1000
READ_COUNT = 200
ROBOTS_S = 2.0  # how often the gateways' robots are read again
UNKNOWN_ROBOT_S = 0.2  # and at most this often when an update names a robot not known (yet)
COUNTS_S = 2.0  # how often refusals are added to the rows
LARGEST = protocol.MAX_LIVE_BYTES
STALE_S = 10.0  # a live update older than this when a relay first reads its stream is not sent
SEND_CONCURRENCY = 20  # groups sent to side by side


class LiveRelay:
    def __init__(self, client: redis.Redis, prefix: str, held: Callable[[], set[str]],
                 quarantine: Callable[[str, str, list[str]], None]) -> None:
        self.redis, self.prefix, self.held, self.quarantine = client, prefix, held, quarantine
        self.last_ids: dict[str, str] = {}  # stream -> last id read
        self.robots: dict[str, dict[str, Robot]] = {}  # gateway -> its robots by exact name
        self.robots_at = 0.0
        self.refused: dict[str, int] = {}
        self.counted_at = 0.0
        self.sent = 0
        self.layer = get_channel_layer()
        self.loop = asyncio.new_event_loop()
        self.sending = asyncio.Semaphore(SEND_CONCURRENCY)  # (a semaphore binds to the loop that first waits)

    # --- the thread ----------------------------------------------------------------------

    def run(self, stopping: threading.Event) -> None:
        keep_turning(self.turn, stopping, "relaying the gateways' live updates", log)
        self.loop.close()

    def turn(self, block_ms: int = BLOCK_MS) -> int:
        """Read what arrived (waiting up to ``block_ms``) and send it on; returns how many sent."""
        names = sorted(self.held())
        streams = {protocol.live_stream(self.prefix, name): name for name in names}
        for gone in set(self.last_ids) - set(streams):
            del self.last_ids[gone]
        if not streams:
            time.sleep(block_ms / 1000)
            return 0
        if time.monotonic() - self.robots_at >= ROBOTS_S or set(names) - set(self.robots):
            self.read_robots(names)
        # A stream new to this relay holds only what nobody read yet (read entries are trimmed):
        # all of it, but for what is too old to show (entry ids are Redis's milliseconds).
        fresh_from = f"{int((time.time() - STALE_S) * 1000)}-0"
        ids = {stream: self.last_ids.setdefault(stream, fresh_from) for stream in streams}
        try:
            replies = self.redis.xread(ids, count=READ_COUNT, block=block_ms)
        except redis.ResponseError as exc:
            if "WRONGTYPE" not in str(exc) and "UNBLOCKED" not in str(exc):
                raise
            self.find_broken(streams)
            return 0
        sent = 0
        for raw_stream, entries in replies or []:
            stream = text(raw_stream)
            if stream in streams and entries:
                self.last_ids[stream] = text(entries[-1][0])
                sent += self.relay(streams[stream], entries)
                self.redis.xtrim(stream, minid=self.last_ids[stream])  # read: nothing more to keep
        self.count_refusals()
        return sent

    def find_broken(self, streams: dict[str, str]) -> None:
        with self.redis.pipeline(transaction=False) as pipe:
            for stream in streams:
                pipe.type(stream)
            types = [text(t) for t in pipe.execute()]
        for name, found in zip(streams.values(), types, strict=True):
            if found not in ("stream", "none"):
                self.quarantine(name, f"its live stream in Redis was replaced by a {found} (deleted by the site)",
                                ["live"])

    def read_robots(self, names: list[str]) -> None:
        robots: dict[str, dict[str, Robot]] = {name: {} for name in names}
        for robot in Robot.objects.filter(gateway__name__in=names).select_related("gateway"):
            robots[robot.gateway.name][robot.name] = robot
        self.robots, self.robots_at = robots, time.monotonic()

    # --- one gateway's updates -----------------------------------------------------------

    def relay(self, gateway: str, entries: list) -> int:
        messages: list[tuple[str, dict]] = []
        for entry, fields in entries:
            raw = fields.get(b"m", fields.get("m")) if isinstance(fields, dict) else None
            if not isinstance(raw, (bytes, str)) or len(raw) > LARGEST:
                size = "no 'm' field" if not isinstance(raw, (bytes, str)) else f"{len(raw):,} bytes"
                self.quarantine(gateway, f"an entry of its live stream ({text(entry)}) has {size} "
                                f"(at most {LARGEST:,} bytes are read)", [])
                break
            try:
                messages += self.check(gateway, json.loads(raw))
            except (ValueError, RecursionError, TypeError, checks.GatewayInputRefused) as exc:
                self.refused[gateway] = self.refused.get(gateway, 0) + 1
                log.info("gateway %s: refused a live update: %s", gateway, exc)
        if messages:
            self.loop.run_until_complete(self.send(messages))
        return len(messages)

    def check(self, gateway: str, message: Any) -> list[tuple[str, dict]]:
        """The (group, message) pairs one update becomes, from its checked fields."""
        if not isinstance(message, dict):
            raise checks.GatewayInputRefused("a live update must be a JSON object")
        robots = self.robots.get(gateway, {})
        robot_named = _robot_named(message)
        if robot_named and robot_named not in robots and time.monotonic() - self.robots_at > UNKNOWN_ROBOT_S:
            self.read_robots(sorted(self.robots))  # a robot added since: read again (not for every message)
            robots = self.robots.get(gateway, {})
        kind = message.get("type")
        if kind == "node.state":
            payload, robot = checks.node_payload(message.get("node"), robots, gateway)
            update = {"type": "node.state", "node": payload}
            groups = [protocol.node_group(payload["id"]), protocol.robot_group(robot.id), protocol.FLEET_GROUP]
        elif kind == "node.parameters":
            key, changes = checks.parameter_update(message, robots, gateway)
            update = {"type": "node.parameters", "node": key, "changes": changes}
            groups = [protocol.node_group(key)]
        elif kind == "run.progress":
            run, robot, keys = checks.run_progress(message, robots, gateway)
            update = {"type": "run.progress", "run": run}
            groups = [protocol.robot_group(robot.id), protocol.FLEET_GROUP, *map(protocol.node_group, keys)]
        else:
            raise checks.GatewayInputRefused(f"unknown live update {str(kind)[:40]!r}")
        return [(group, update) for group in groups]

    async def send(self, messages: list[tuple[str, dict]]) -> None:
        """Each group's updates in order (a page sees a node's states as they came), the groups
        side by side."""
        by_group: dict[str, list[dict]] = {}
        for group, message in messages:
            by_group.setdefault(group, []).append(message)

        async def in_order(group: str, updates: list[dict]) -> list:
            results: list = []
            async with self.sending:  # the channel layer's pool holds 100 connections: a burst beyond fails
                for update in updates:
                    try:
                        await self.layer.group_send(group, update)
                        results.append(None)
                    except Exception as exc:  # noqa: BLE001 - Redis down or full: the pages catch up on reload
                        results.append(exc)
            return results

        done = await asyncio.gather(*(in_order(g, u) for g, u in by_group.items()))
        failures = [r for results in done for r in results if r is not None]
        self.sent += len(messages) - len(failures)
        if failures:
            log.warning("could not send %d of %d live updates: %s", len(failures), len(messages), failures[0])

    def count_refusals(self) -> None:
        if not self.refused or time.monotonic() - self.counted_at < COUNTS_S:
            return
        refused, self.refused = self.refused, {}
        self.counted_at = time.monotonic()
        for name, count in refused.items():
            Gateway.objects.filter(name=name).update(live_refused=F("live_refused") + count)


def _robot_named(message: dict) -> str:
    """The robot a live update says it is about (before any check)."""
    for holder in (message.get("node"), message.get("run"), message):
        if isinstance(holder, dict) and isinstance(holder.get("robot"), str):
            return holder["robot"]
    return ""
