"""A ROS domain's /rosout, read by a thread of its own from a node outside the domain's executors:
a flooding logger must not slow transition events and service replies (an executor rebuilds its
wait set over every entity for each message it takes). A quiet /rosout costs nothing: the
thread waits on the subscription and on a guard condition that ``stop()`` triggers."""
from __future__ import annotations

import logging
import threading
from typing import Any, Callable

import rclpy.node
from rcl_interfaces.msg import Log
from rclpy.guard_condition import GuardCondition
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

log = logging.getLogger(__name__)

# Messages taken per wake-up at most, so a flood cannot starve the thread's stop check.
ROSOUT_BATCH = 1000
WAIT_BOUND_NS = 5_000_000_000  # a safeguard only: stop() wakes the wait
ROSOUT_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=200,
    reliability=ReliabilityPolicy.RELIABLE,
    # Transient local: records a node logged just before we subscribed still arrive.
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)


class RosoutReader:
    """Hands every /rosout message of ``node``'s domain to ``on_log(domain_id, message)``, on its thread."""

    def __init__(self, node: rclpy.node.Node, domain_id: int, on_log: Callable[[int, Any], None]) -> None:
        self.node, self.domain_id, self.on_log = node, domain_id, on_log
        self._subscription = node.create_subscription(Log, "/rosout", lambda _msg: None, ROSOUT_QOS)
        self._wake = GuardCondition(None, None, context=node.context)
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._drain, name=f"ros-rosout-{domain_id}", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        self._stopping.set()
        self._wake.trigger()
        self._thread.join(timeout=timeout)

    def _drain(self) -> None:
        """Wait on /rosout and take every waiting message per wake-up."""
        context = self.node.context
        wait_set = _rclpy.WaitSet(1, 1, 0, 0, 0, 0, context.handle)
        handle, wake = self._subscription.handle, self._wake.handle
        try:
            while not self._stopping.is_set() and context.ok():
                wait_set.clear_entities()
                wait_set.add_subscription(handle)
                wait_set.add_guard_condition(wake)
                wait_set.wait(WAIT_BOUND_NS)
                if handle.pointer not in wait_set.get_ready_entities("subscription"):
                    continue
                for _ in range(ROSOUT_BATCH):
                    taken = handle.take_message(Log, False)
                    if taken is None:
                        break
                    self.on_log(self.domain_id, taken[0])
        except Exception:  # shutting down (invalid handle, context gone) or a bug: say so once
            if not self._stopping.is_set():
                log.exception("reading /rosout of ROS domain %d stopped", self.domain_id)
