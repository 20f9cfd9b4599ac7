"""How often the topics a robot's current mode waits for are published (a readiness predicate
"/scan at >= 5 Hz over 5 s"), measured by the gateway without decoding a message: each is
subscribed raw (best effort, which any publisher matches) on a node of its own per domain, and
only the arrival times are kept, at most MAX_KEPT per topic. The site is told the rates every
REPORT_S when one moved by more than a tenth (or to or from none), and every RESEND_S anyway."""
from __future__ import annotations

import importlib
import logging
import math
import re
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from rclpy.qos import qos_profile_sensor_data

from ros_gateway.outbox import Outbox
from ros_gateway.registry import NodeRegistry
from ros_gateway.shared import protocol

log = logging.getLogger(__name__)

MAX_KEPT = 20_000  # arrival times per topic (a rate above MAX_KEPT / window is reported as that)
REPORT_S, RESEND_S = 1.0, 30.0
WINDOW_RANGE = (0.5, 60.0)
TOPIC_RE = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")
TYPE_RE = re.compile(r"^([a-z][a-z0-9_]*)/msg/([A-Z][A-Za-z0-9]*)$")


@dataclass
class _Meter:
    window_s: float
    since: float = field(default_factory=time.monotonic)
    arrivals: deque = field(default_factory=lambda: deque(maxlen=MAX_KEPT))
    subscription: Any = None
    type_name: str = ""

    def rate(self, now: float) -> float | None:
        """Messages per second over the window (or since subscribed, if shorter); None: no publisher."""
        while self.arrivals and self.arrivals[0] < now - self.window_s:
            self.arrivals.popleft()
        span = min(self.window_s, now - self.since)
        if self.subscription is None or span <= 0:
            return None
        return round(len(self.arrivals) / span, 2)


def message_class(type_name: str) -> Any:
    """The message class of "pkg/msg/Type", if this gateway has its package (None if not)."""
    found = TYPE_RE.match(type_name)
    if found is None:
        return None
    try:
        return getattr(importlib.import_module(f"{found.group(1)}.msg"), found.group(2))
    except (ImportError, AttributeError):
        return None


class TopicRates:
    def __init__(self, registry: NodeRegistry, domains: dict, outbox: Outbox) -> None:
        self.registry, self.domains, self.outbox = registry, domains, outbox
        self.meters: dict[tuple[int, str], dict[str, _Meter]] = {}  # (robot id, domain) -> topic -> meter
        self.sent: dict[int, tuple[float, dict[str, float | None]]] = {}  # robot id -> (when, rates)

    def apply(self, config: dict) -> None:
        """The topics each watched robot's config asks to be measured; others are let go."""
        wanted: dict[tuple[int, int], dict[str, float]] = {}
        for entry in config.get("robots") or []:
            robot = self.registry.robots.get(entry.get("id")) if isinstance(entry, dict) else None
            rates = entry.get("rates") if robot is not None else None
            if not isinstance(rates, list):
                continue
            topics = wanted.setdefault((robot.id, robot.domain_id), {})
            for item in rates[:protocol.MAX_RATE_TOPICS]:
                topic, window = (item.get("topic"), item.get("window_s")) if isinstance(item, dict) else (None, None)
                if isinstance(topic, str) and TOPIC_RE.match(topic) and isinstance(window, (int, float)) \
                        and math.isfinite(window):
                    topics[topic] = min(max(float(window), WINDOW_RANGE[0]), WINDOW_RANGE[1])
        for key in set(self.meters) - set(wanted):
            self._drop(key, set(self.meters[key]))
            del self.meters[key]
            self.sent.pop(key[0], None)
        for key, topics in wanted.items():
            meters = self.meters.setdefault(key, {})
            self._drop(key, set(meters) - set(topics))
            for topic, window in topics.items():
                meters.setdefault(topic, _Meter(window)).window_s = window

    def _drop(self, key: tuple[int, int], topics: set[str]) -> None:
        domain = self.domains.get(key[1])
        for topic in topics:
            meter = self.meters[key].pop(topic)
            if meter.subscription is not None and domain is not None:
                domain.meter_node().destroy_subscription(meter.subscription)

    def _subscribe(self, domain, topic: str, meter: _Meter, types: dict[str, list[str]]) -> None:
        """Subscribe once the topic is in the graph with a type this gateway knows."""
        for type_name in types.get(topic, []):
            cls = message_class(type_name)
            if cls is None:
                continue
            meter.subscription = domain.meter_node().create_subscription(
                cls, topic, lambda _raw, arrivals=meter.arrivals: arrivals.append(time.monotonic()),
                qos_profile_sensor_data, raw=True)
            meter.type_name, meter.since = type_name, time.monotonic()
            log.info("measuring the rate of %s (%s) in ROS domain %d", topic, type_name, domain.domain_id)
            return

    async def report(self) -> None:
        now = time.monotonic()
        for (robot_id, domain_id), meters in list(self.meters.items()):
            robot, domain = self.registry.robots.get(robot_id), self.domains.get(domain_id)
            if robot is None or domain is None:
                continue
            missing = [t for t, m in meters.items() if m.subscription is None]
            types = domain.topic_types() if missing else {}
            for topic in missing:
                self._subscribe(domain, topic, meters[topic], types)
            rates = {topic: meter.rate(now) for topic, meter in meters.items()}
            when, before = self.sent.get(robot_id, (-math.inf, {}))
            if now - when < RESEND_S and not any(_moved(before.get(t), r) for t, r in rates.items()):
                continue
            self.sent[robot_id] = (now, rates)
            self.outbox.emit(protocol.TOPIC_RATES, robot=robot.name,
                             rates=[{"topic": t, "hz": r, "window_s": meters[t].window_s} for t, r in rates.items()])


def _moved(before: float | None, now: float | None) -> bool:
    if (before is None) != (now is None):
        return True
    return before is not None and abs(now - before) > max(0.5, 0.1 * before)
