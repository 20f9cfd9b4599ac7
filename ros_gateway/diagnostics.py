"""Each watched robot's health as its nodes report it on ``/diagnostics`` and ``/diagnostics_agg``
(diagnostic_msgs/DiagnosticArray, in the robot's namespace), kept here as the latest status per
name and sent to the site as it changes.

Messages are taken on the domain's meter node (an executor thread of its own) and decoded there;
only what the site needs leaves: a status whose level or message changed (or that went stale, or
is new) within URGENT_GATHER_S, its key/values when they changed at most every
DIAGNOSTICS_REFRESH_S, and the names of statuses heard again unchanged as often (so a page can
say how fresh they are). A status not heard for the site's stale time is sent as stale.
Everything is bounded: statuses per robot (the rest counted as left out), text lengths,
key/values per status, statuses per fact.
"""
from __future__ import annotations

import asyncio
import json
import logging
import threading
import time
from dataclasses import dataclass
from typing import Any

from rclpy.qos import QoSProfile, ReliabilityPolicy

from ros_gateway.outbox import Outbox
from ros_gateway.registry import NodeRegistry, RobotInfo
from ros_gateway.shared import protocol

log = logging.getLogger(__name__)

URGENT_GATHER_S = 0.02  # level changes this close together go in one fact
TICK_S = 0.5  # how often staleness and refreshes are looked at
PUBLISHERS_S = 5.0  # how often the topics' publishers are read from the graph
MAX_ARRAY = 2 * protocol.MAX_STATUSES  # statuses read of one message
FACT_BYTES = protocol.MAX_FACT_BYTES // 2  # statuses' JSON per fact (the names heard again come on top)
# Best effort matches every publisher (diagnostic_updater's are reliable); a local burst of 20
# arrays is far more than 1-10 Hz needs.
QOS = QoSProfile(depth=20, reliability=ReliabilityPolicy.BEST_EFFORT)

try:  # the gateway's own environment has it; a gateway without it reports no diagnostics
    from diagnostic_msgs.msg import DiagnosticArray
except ImportError:  # pragma: no cover - depends on the installation
    DiagnosticArray = None


def _cut(text: Any, limit: int) -> str:
    text = str(text)
    return text if len(text) <= limit else text[: limit - 1] + "…"


def level_of(raw: Any) -> int:
    """A DiagnosticStatus level (a ``byte`` field: bytes in rclpy) as 0-3; an unknown one is ERROR."""
    value = raw[0] if isinstance(raw, (bytes, bytearray)) and raw else raw
    return value if isinstance(value, int) and 0 <= value <= 3 else 2


@dataclass
class _Status:
    level: int
    message: str
    hardware_id: str
    values: tuple
    topic: str
    heard: float  # monotonic
    node: str = ""  # the node that reports it, where known (publisher)
    stale: bool = False
    changed: bool = True  # content not sent yet
    urgent: bool = True  # level, message or staleness changed (or new): sent at once
    heard_again: bool = False  # heard unchanged since last sent
    sent_at: float = 0.0


class _Robot:
    """One robot's statuses; written by the executor thread, read by the gateway's loop (under lock)."""

    def __init__(self, info: RobotInfo) -> None:
        self.info = info
        self.statuses: dict[str, _Status] = {}
        self.left_out = 0
        self.lock = threading.Lock()
        self.subscriptions: dict[str, Any] = {}  # topic -> subscription
        self.publishers: dict[str, list[str]] = {}  # topic -> publishing nodes (fully qualified)

    def topics(self) -> list[str]:
        base = self.info.namespace.rstrip("/")
        return [f"{base}/{name}" for name in protocol.DIAGNOSTIC_TOPICS]

    def take(self, message: Any, topic: str, wake: Any) -> None:
        """A DiagnosticArray arrived (in the executor thread)."""
        now = time.monotonic()
        urgent = False
        with self.lock:
            for raw in message.status[:MAX_ARRAY]:
                name = _cut(raw.name, protocol.MAX_STATUS_NAME) or "(no name)"
                level, text = level_of(raw.level), _cut(raw.message, protocol.MAX_STATUS_MESSAGE)
                values = tuple((_cut(v.key, protocol.MAX_VALUE_KEY), _cut(v.value, protocol.MAX_VALUE_TEXT))
                               for v in raw.values[:protocol.MAX_STATUS_VALUES])
                hardware_id = _cut(raw.hardware_id, protocol.MAX_HARDWARE_ID)
                status = self.statuses.get(name)
                if status is None:
                    if len(self.statuses) >= protocol.MAX_STATUSES:
                        self.left_out += 1
                        continue
                    self.statuses[name] = _Status(level, text, hardware_id, values, topic, now,
                                                  self.publisher(name, topic))
                    urgent = True
                    continue
                status.heard = now
                if status.level != level or status.message != text or status.stale:
                    status.level, status.message, status.stale = level, text, False
                    status.values, status.topic, status.hardware_id = values, topic, hardware_id
                    status.changed = status.urgent = urgent = True
                elif status.values != values or status.topic != topic or status.hardware_id != hardware_id:
                    status.values, status.topic, status.hardware_id, status.changed = values, topic, hardware_id, True
                else:
                    status.heard_again = True
        if urgent:
            wake()

    def read_publishers(self, domain: Any) -> None:
        """The nodes publishing the robot's diagnostics, from the graph; statuses whose reporting node
        this tells (or changes) are sent again."""
        for topic in self.topics():
            try:
                found = domain.node.get_publishers_info_by_topic(topic)
            except Exception:  # noqa: BLE001 - the graph is being torn down
                continue
            self.publishers[topic] = sorted({
                (f"{i.node_namespace.rstrip('/')}/{i.node_name}") for i in found
                if not i.node_name.startswith("lifecycle_gateway_")})[:64]
        with self.lock:
            by_hardware: dict[str, str] = {}  # hardware id -> node, of the statuses not aggregated
            for name, status in self.statuses.items():
                if status.hardware_id and not status.topic.endswith("_agg"):
                    found = self.publisher(name, status.topic)
                    by_hardware[status.hardware_id] = found if by_hardware.get(status.hardware_id, found) == found \
                        else ""  # (two nodes, one id: not known)
            for name, status in self.statuses.items():
                node = self.publisher(name, status.topic, status.hardware_id, by_hardware)
                if node != status.node:
                    status.node, status.changed = node, True

    def publisher(self, name: str, topic: str, hardware_id: str = "", by_hardware: dict | None = None) -> str:
        """The node that reports a status, where known: named as diagnostic_updater does ("node: task",
        also as an aggregated path's last part) among the nodes publishing diagnostics; for an aggregated
        status, the node of the status it sums up (diagnostic_aggregator keeps its hardware id); or the
        only node publishing the topic."""
        if by_hardware and by_hardware.get(hardware_id) and topic.endswith("_agg"):
            return by_hardware[hardware_id]
        direct = self.publishers.get(topic, [])
        reporters = direct + [n for t, nodes in self.publishers.items() if t != topic for n in nodes]
        prefix = name.rsplit("/", 1)[-1].split(":", 1)[0].strip() if ":" in name else ""
        if prefix:
            for node in reporters:
                if node.rsplit("/", 1)[-1] == prefix or node == prefix:
                    return node
        return direct[0] if len(direct) == 1 and not topic.endswith("_agg") else ""

    def due(self, now: float, stale_s: float) -> tuple[list[tuple[str, _Status]], list[str], bool]:
        """(statuses to send, names heard again, any urgent), marked as sent."""
        send, heard, urgent = [], [], False
        with self.lock:
            for name, status in self.statuses.items():
                if not status.stale and now - status.heard > stale_s:
                    status.stale = status.changed = status.urgent = True
                refresh = now - status.sent_at >= protocol.DIAGNOSTICS_REFRESH_S
                if status.urgent or status.changed and refresh:
                    urgent |= status.urgent
                    send.append((name, _Status(**status.__dict__)))
                    status.changed = status.urgent = status.heard_again = False
                    status.sent_at = now
                elif status.heard_again and refresh:
                    heard.append(name)
                    status.heard_again, status.sent_at = False, now
        return send, heard, urgent


def parts(statuses: list[dict]) -> list[list[dict]]:
    """The statuses in facts of at most MAX_STATUSES_PER_FACT and FACT_BYTES each (a status with every
    text and key/value at its limit takes about 11 KB; the site refuses a fact over MAX_FACT_BYTES)."""
    found: list[list[dict]] = []
    size = 0
    for entry in statuses:
        length = len(json.dumps(entry))
        if not found or len(found[-1]) >= protocol.MAX_STATUSES_PER_FACT or size + length > FACT_BYTES:
            found.append([])
            size = 0
        found[-1].append(entry)
        size += length
    return found


class Diagnostics:
    def __init__(self, registry: NodeRegistry, domains: dict, outbox: Outbox) -> None:
        self.registry, self.domains, self.outbox = registry, domains, outbox
        self.robots: dict[int, _Robot] = {}
        self.stale_s = protocol.DEFAULT_DIAGNOSTICS_STALE_S
        self.left_out_sent: dict[int, int] = {}
        self.publishers_at = 0.0
        self._wake = asyncio.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        if DiagnosticArray is None:
            log.warning("diagnostic_msgs is not installed here: the robots' /diagnostics are not watched")

    def apply(self, config: dict) -> None:
        """Watch the diagnostics of the config's robots (as the registry holds them); let others go."""
        limits = config.get("limits") if isinstance(config.get("limits"), dict) else {}
        stale = limits.get("diagnostics_stale_s")
        if isinstance(stale, (int, float)) and 0.5 <= stale <= 3600:
            self.stale_s = float(stale)
        wanted = {r.id: r for r in self.registry.robots.values()} if DiagnosticArray is not None else {}
        for robot_id in set(self.robots) - set(wanted):
            self._drop(self.robots.pop(robot_id))
        for robot_id, info in wanted.items():
            kept = self.robots.get(robot_id)
            if kept is not None and (kept.info.domain_id, kept.info.namespace) != (info.domain_id, info.namespace):
                self._drop(self.robots.pop(robot_id))
                kept = None
            if kept is None:
                self.robots[robot_id] = _Robot(info)
            else:
                kept.info = info

    def _drop(self, robot: _Robot) -> None:
        domain = self.domains.get(robot.info.domain_id)
        for subscription in robot.subscriptions.values():
            if domain is not None:
                domain.meter_node().destroy_subscription(subscription)
        robot.subscriptions.clear()

    def _subscribe(self, robot: _Robot) -> None:
        domain = self.domains.get(robot.info.domain_id)
        if domain is None:
            return  # its domain is not watched yet (discovery starts it)
        for topic in robot.topics():
            if topic not in robot.subscriptions:
                robot.subscriptions[topic] = domain.meter_node().create_subscription(
                    DiagnosticArray, topic, lambda message, topic=topic, robot=robot: robot.take(
                        message, topic, self._wake_soon), QOS)

    def _wake_soon(self) -> None:
        if self._loop is not None:
            self._loop.call_soon_threadsafe(self._wake.set)

    async def run(self, stopping: asyncio.Event) -> None:
        self._loop = asyncio.get_running_loop()
        while not stopping.is_set():
            try:
                await asyncio.wait_for(self._wake.wait(), TICK_S)
                await asyncio.sleep(URGENT_GATHER_S)  # what comes with it goes in the same fact
            except asyncio.TimeoutError:
                pass
            self._wake.clear()
            try:
                self.report()
            except Exception:  # noqa: BLE001 - logged; the next tick tries again
                log.exception("reporting the robots' diagnostics failed")

    def report(self) -> None:
        now = time.monotonic()
        read_publishers = now - self.publishers_at >= PUBLISHERS_S
        if read_publishers:
            self.publishers_at = now
        for robot in list(self.robots.values()):
            if len(robot.subscriptions) < len(protocol.DIAGNOSTIC_TOPICS):
                self._subscribe(robot)
            if read_publishers:
                self._read_publishers(robot)
            send, heard, _ = robot.due(now, self.stale_s)
            left_out = robot.left_out
            if not send and not heard and left_out == self.left_out_sent.get(robot.info.id, 0):
                continue
            self.left_out_sent[robot.info.id] = left_out
            statuses = [self._entry(robot, name, status, now) for name, status in send]
            for index, part in enumerate(parts(statuses) or [[]]):
                self.outbox.emit(protocol.DIAGNOSTICS, robot=robot.info.name, statuses=part,
                                 heard=heard if index == 0 else [], left_out=left_out)

    def _read_publishers(self, robot: _Robot) -> None:
        domain = self.domains.get(robot.info.domain_id)
        if domain is not None and domain.node is not None:
            robot.read_publishers(domain)

    def _entry(self, robot: _Robot, name: str, status: _Status, now: float) -> dict:
        return {"name": name, "level": status.level, "message": status.message, "hardware_id": status.hardware_id,
                "values": [list(pair) for pair in status.values], "topic": status.topic,
                "node": status.node, "stale": status.stale,
                "age_s": round(max(0.0, now - status.heard), 3)}
