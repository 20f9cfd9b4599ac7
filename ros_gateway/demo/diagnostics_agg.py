"""A small diagnostic_aggregator for one demo robot: ``diagnostics`` in, ``diagnostics_agg`` out.

Statuses are sorted into a tree by their names (``"<node name>: <task>"``): ``lidar_driver:
Scan rate`` becomes ``/AGV1/Sensors/Lidar``, ``battery_monitor: Battery`` ``/AGV1/Power/Battery``
(when a component has several statuses, each gets a leaf ``.../<Component>/<task>``). Every
parent path gets a status too, as diagnostic_aggregator's analyzers publish them: the worst level
of its children, where stale children count as errors unless all of them are stale. A status not
heard for `STALE_AFTER_S` is reported STALE with its last values.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node

from .diagnostics import ERROR, OK, PERIOD_S, QOS, STALE, TOPIC, WARN, level_of

AGG_TOPIC = "diagnostics_agg"  # relative, like TOPIC
STALE_AFTER_S = 5.0
#: (group, component, substrings of the node name part), first match wins
RULES: tuple[tuple[str, str, tuple[str, ...]], ...] = (
    ("Sensors", "Lidar", ("lidar", "laser", "scan")),
    ("Sensors", "Camera", ("camera",)),
    ("Power", "Battery", ("battery", "power", "bms")),
    ("Drivers", "Flaky node", ("flaky",)),
    ("Drivers", "Motors", ("motor",)),
)
OTHER_GROUP = "Other"  # unmatched statuses: /<Robot>/Other/<node name>
PARENT_WORDS = {OK: "OK", WARN: "warning", ERROR: "error", STALE: "stale"}


def robot_name(namespace: str) -> str:
    """``/agv1`` -> ``AGV1`` (the last namespace segment), no namespace -> ``Robot``."""
    last = namespace.strip("/").rpartition("/")[2]
    return last.upper() if last else "Robot"


def split_name(name: str) -> tuple[str, str]:
    """``"lidar_driver: Scan rate"`` -> (``lidar_driver``, ``Scan rate``); no colon: (name, name)."""
    node, sep, task = name.partition(":")
    return (node.strip(), task.strip()) if sep else (name.strip(), name.strip())


def classify(name: str) -> tuple[str, str]:
    """(group, component) of a status by its node name part."""
    node, _ = split_name(name)
    lowered = node.lower()
    for group, component, words in RULES:
        if any(word in lowered for word in words):
            return group, component
    return OTHER_GROUP, node or "unnamed"


def combine(levels: list[int]) -> int:
    """A parent's level: the worst child; stale children count as errors unless all are stale
    (diagnostic_aggregator's rule: one silent sensor is an error of its group, not a silent group)."""
    if not levels:
        return STALE
    worst = max(levels)
    if worst == STALE and not all(level == STALE for level in levels):
        return ERROR
    return worst


@dataclass
class _Heard:
    status: DiagnosticStatus
    at: float  # time.monotonic()


class Aggregate:
    """The latest status per name and when it came; `report()` builds the tree (no ROS needed)."""

    def __init__(self, robot: str, stale_after_s: float = STALE_AFTER_S) -> None:
        self.robot, self.stale_after_s = robot, stale_after_s
        self._heard: dict[str, _Heard] = {}

    def add(self, status: DiagnosticStatus, now: float) -> None:
        self._heard[status.name] = _Heard(status, now)

    def paths(self) -> dict[str, str]:
        """Status name -> its leaf path."""
        bases = {name: "/{}/{}/{}".format(self.robot, *classify(name)) for name in self._heard}
        shared = {base for base in bases.values() if list(bases.values()).count(base) > 1}
        return {
            name: f"{base}/{split_name(name)[1]}" if base in shared else base for name, base in bases.items()
        }

    def report(self, now: float) -> list[DiagnosticStatus]:
        root = f"/{self.robot}"
        if not self._heard:
            return [DiagnosticStatus(level=bytes([STALE]), name=root, message="no diagnostics received")]
        out: dict[str, DiagnosticStatus] = {}
        children: dict[str, list[str]] = {}
        for name, path in self.paths().items():
            heard = self._heard[name]
            stale = now - heard.at > self.stale_after_s
            out[path] = DiagnosticStatus(
                level=bytes([STALE]) if stale else bytes([level_of(heard.status)]),
                name=path,
                message="stale" if stale else heard.status.message,
                hardware_id=heard.status.hardware_id,
                values=list(heard.status.values),
            )
            child = path
            while child != root:
                parent = child.rpartition("/")[0]
                siblings = children.setdefault(parent, [])
                if child not in siblings:
                    siblings.append(child)
                child = parent
        # deepest parents first, so that each parent's children are known when it is built
        for parent in sorted(children, key=lambda p: p.count("/"), reverse=True):
            kids = [out[c] for c in sorted(children[parent])]
            level = combine([level_of(k) for k in kids])
            message = PARENT_WORDS[level]
            if level != OK:
                worst = [k.name.rpartition("/")[2] for k in kids if level_of(k) >= min(level, ERROR)]
                message += ": " + ", ".join(worst)
            out[parent] = DiagnosticStatus(
                level=bytes([level]),
                name=parent,
                message=message,
                values=[KeyValue(key=k.name.rpartition("/")[2], value=k.message) for k in kids],
            )
        return [out[path] for path in sorted(out)]


class DiagnosticAggregator(Node):
    """Plain node aggregating the robot's ``diagnostics`` into ``diagnostics_agg`` once a second
    (robot process option ``--diagnostics-agg``)."""

    NAME = "diagnostic_aggregator"

    def __init__(self, node_name: str = NAME, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.aggregate = Aggregate(robot_name(self.get_namespace()))
        # subscription and timer share the node's mutually exclusive default group: no lock needed
        self.create_subscription(DiagnosticArray, TOPIC, self._on_diagnostics, QOS)
        self._pub = self.create_publisher(DiagnosticArray, AGG_TOPIC, QOS)
        self.create_timer(PERIOD_S, self._publish)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        now = time.monotonic()
        for status in msg.status:
            self.aggregate.add(status, now)

    def _publish(self) -> None:
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = self.aggregate.report(time.monotonic())
        self._pub.publish(msg)
