"""ROS 2 diagnostics for the demo robot, the way diagnostic_updater based drivers publish them.

* `StatusPublisher`: attached to a node, publishes its tasks' statuses (named
  ``"<node name>: <task>"``, with a hardware id) as one ``diagnostic_msgs/DiagnosticArray`` per
  second on the relative topic ``diagnostics`` (so it lands in the robot's namespace).
* `EventWindow`: event times in a sliding window (a rate, a sum), for frequency checks.
* `BatteryMonitor`: a plain node simulating a battery that drains and recharges in a loop.

The aggregator (``diagnostics_agg``) lives in `diagnostics_agg`.
"""

from __future__ import annotations

import collections
import random
import threading
import time
from typing import Any, Callable, Optional

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from .base import declare_parameter

OK, WARN, ERROR, STALE = 0, 1, 2, 3
LEVEL_NAMES = {OK: "OK", WARN: "WARN", ERROR: "ERROR", STALE: "STALE"}
TOPIC = "diagnostics"  # relative: /<namespace>/diagnostics
PERIOD_S = 1.0
# diagnostic_updater's publisher: reliable, volatile, keep last
QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)

#: what a task reports: (level, message, key/values)
Report = tuple[int, str, dict[str, Any]]


def level_of(status: DiagnosticStatus) -> int:
    """The status level as an int (``byte`` fields arrive as ``bytes`` in rclpy)."""
    level = status.level
    return level[0] if isinstance(level, (bytes, bytearray)) else int(level)


def format_value(value: Any) -> str:
    """KeyValue values are strings: floats with two decimals, booleans lower case."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:.2f}"
    return str(value)


def make_status(name: str, hardware_id: str, level: int, message: str, values: dict[str, Any]) -> DiagnosticStatus:
    return DiagnosticStatus(
        level=bytes([level]),
        name=name,
        message=message,
        hardware_id=hardware_id,
        values=[KeyValue(key=k, value=format_value(v)) for k, v in values.items()],
    )


class StatusPublisher:
    """A minimal diagnostic_updater: ``tasks`` (task name -> report function) published at 1 Hz.

    The timer has a callback group of its own so that statuses keep coming while the node is
    busy in a (slow or hanging) transition on another executor thread. ``alive()`` turning
    False (e.g. the node finalized) stops the publishing for good: a node that is gone says
    nothing, which an aggregator reports as stale.
    """

    def __init__(
        self,
        node: Node,
        hardware_id: str,
        tasks: dict[str, Callable[[], Report]],
        alive: Callable[[], bool] = lambda: True,
        period_s: float = PERIOD_S,
    ) -> None:
        self.node, self.hardware_id, self.tasks, self.alive = node, hardware_id, tasks, alive
        self._pub = node.create_publisher(DiagnosticArray, TOPIC, QOS)
        self._timer = node.create_timer(period_s, self.publish, callback_group=MutuallyExclusiveCallbackGroup())

    def statuses(self) -> list[DiagnosticStatus]:
        prefix = self.node.get_name()
        out = []
        for task, report in self.tasks.items():
            try:
                level, message, values = report()
            except Exception as exc:  # noqa: BLE001 - a broken check is an error, not a dead timer
                level, message, values = ERROR, f"diagnostic task failed: {type(exc).__name__}: {exc}", {}
            out.append(make_status(f"{prefix}: {task}", self.hardware_id, level, message, values))
        return out

    def publish(self) -> None:
        if not self.alive():
            self._timer.cancel()
            return
        msg = DiagnosticArray()
        msg.header.stamp = self.node.get_clock().now().to_msg()
        msg.status = self.statuses()
        self._pub.publish(msg)


class EventWindow:
    """Times (and amounts) of events within the last ``window_s`` seconds; thread safe."""

    def __init__(self, window_s: float = 5.0) -> None:
        self.window_s = window_s
        self._events: collections.deque[tuple[float, float]] = collections.deque()
        self._lock = threading.Lock()
        self.since = time.monotonic()

    def restart(self) -> None:
        with self._lock:
            self._events.clear()
            self.since = time.monotonic()

    def add(self, amount: float = 1.0, now: Optional[float] = None) -> None:
        now = time.monotonic() if now is None else now
        with self._lock:
            self._events.append((now, amount))
            self._prune(now)

    def _prune(self, now: float) -> None:
        while self._events and self._events[0][0] <= now - self.window_s:
            self._events.popleft()

    def snapshot(self, now: float) -> list[tuple[float, float]]:
        with self._lock:
            self._prune(now)
            return list(self._events)

    def total(self, now: Optional[float] = None) -> float:
        now = time.monotonic() if now is None else now
        return sum(amount for _, amount in self.snapshot(now))

    def frequency(self, now: Optional[float] = None) -> float:
        """Events per second from the intervals between the events in the window (so a window
        only partly filled since `restart` is not read as a low rate); 0 with fewer than two."""
        now = time.monotonic() if now is None else now
        times = [t for t, _ in self.snapshot(now)]
        if len(times) < 2 or times[-1] <= times[0]:
            return 0.0
        return (len(times) - 1) / (times[-1] - times[0])

    def last(self, now: Optional[float] = None) -> Optional[float]:
        now = time.monotonic() if now is None else now
        events = self.snapshot(now)
        return events[-1][0] if events else None


# -- battery ----------------------------------------------------------------------------
BATTERY_WARN_PERCENT, BATTERY_ERROR_PERCENT = 20.0, 10.0
DOCK_AT_PERCENT = 8.0  # the simulated robot goes charging this late, so each cycle shows WARN and ERROR
EMPTY_V, FULL_V = 21.0, 29.4  # a 7-cell Li-ion pack (24 V nominal)


class BatteryModel:
    """Charge that drains until `DOCK_AT_PERCENT`, then recharges to 100 %, in a loop."""

    def __init__(self, percent: float) -> None:
        self.percent = percent
        self.charging = False

    def step(self, dt_s: float, drain_per_min: float, charge_per_min: float) -> None:
        if self.charging:
            self.percent = min(100.0, self.percent + charge_per_min * dt_s / 60.0)
            self.charging = self.percent < 100.0
        else:
            self.percent = max(0.0, self.percent - drain_per_min * dt_s / 60.0)
            self.charging = self.percent <= DOCK_AT_PERCENT

    @property
    def voltage(self) -> float:
        return EMPTY_V + (FULL_V - EMPTY_V) * self.percent / 100.0 + (0.4 if self.charging else 0.0)

    @property
    def current(self) -> float:
        """Amperes into the pack (negative while discharging)."""
        return 12.0 if self.charging else -3.5

    def report(self) -> Report:
        if self.percent < BATTERY_ERROR_PERCENT:
            level, message = ERROR, "battery critical"
        elif self.percent < BATTERY_WARN_PERCENT:
            level, message = WARN, "battery low"
        else:
            level, message = OK, "battery OK"
        message += ", charging" if self.charging else ", discharging"
        values = {
            "percentage": self.percent,
            "voltage_v": self.voltage,
            "current_a": self.current,
            "charging": self.charging,
            "warn_below_percent": BATTERY_WARN_PERCENT,
            "error_below_percent": BATTERY_ERROR_PERCENT,
        }
        return level, message, values


class BatteryMonitor(Node):
    """Plain node publishing ``battery_monitor: Battery`` on ``diagnostics`` (no demo node runs
    on every robot, so the battery gets a node of its own in the robot process).

    Setting ``initial_percent`` while running jumps the charge there (handy in a demo).
    """

    NAME = "battery_monitor"
    HARDWARE_ID = "sim_bms"

    def __init__(self, node_name: str = NAME, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        start = declare_parameter(
            self, "initial_percent", 80.0, "Charge at start (setting it later jumps there)",
            min_value=0.0, max_value=100.0,
        )
        declare_parameter(self, "drain_percent_per_min", 2.0, "Discharge rate", min_value=0.0, max_value=100.0)
        declare_parameter(self, "charge_percent_per_min", 10.0, "Charge rate", min_value=0.0, max_value=100.0)
        self.model = BatteryModel(start)
        self._rng = random.Random()
        self._last_step = time.monotonic()
        self._last_level: Optional[int] = None
        self.add_post_set_parameters_callback(self._on_params_set)
        self.diagnostics = StatusPublisher(self, self.HARDWARE_ID, {"Battery": self._battery})

    def _on_params_set(self, params: list) -> None:
        for p in params:
            if p.name == "initial_percent":
                self.model.percent, self.model.charging = float(p.value), False

    def _battery(self) -> Report:
        now = time.monotonic()
        self.model.step(
            now - self._last_step,
            self.get_parameter("drain_percent_per_min").value,
            self.get_parameter("charge_percent_per_min").value,
        )
        self._last_step = now
        level, message, values = self.model.report()
        values["voltage_v"] += self._rng.gauss(0.0, 0.02)  # measurement noise
        if level != self._last_level:
            text = f"{message} ({self.model.percent:.1f} %)"
            # one call site per severity: rclpy refuses a call site whose severity changes
            if level == ERROR:
                self.get_logger().error(text)
            elif level == WARN:
                self.get_logger().warn(text)
            elif self._last_level is not None:
                self.get_logger().info(text)
            self._last_level = level
        return level, message, values
