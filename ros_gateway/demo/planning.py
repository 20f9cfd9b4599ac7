"""A toy path planner: consumes ``scan``, publishes a ``plan`` (nav_msgs/Path)."""

from __future__ import annotations

import math
import random
import time
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import LaserScan

from .base import SUCCESS, LifecycleState, PeriodicNode, TransitionCallbackReturn

SCAN_TIMEOUT_S = 2.0


class Planner(PeriodicNode):
    """Lifecycle planner publishing a curved path towards a goal at a low rate."""

    RATE_PARAMETER, RATE_NAME = "planner_frequency_hz", "planner frequency"

    def __init__(self, node_name: str = "planner", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.declare("global_frame", "map", "Frame of the published plan", read_only=True)
        self.declare("planner_frequency_hz", 1.0, "Replanning rate while active", min_value=0.1, max_value=10.0)
        self.declare(
            "tolerance_m", 0.25, "Obstacle clearance required around the robot (m)", min_value=0.01, max_value=2.0
        )
        self.declare("goal_x", 5.0, "Goal x in the global frame (m)", min_value=-50.0, max_value=50.0)
        self.declare("goal_y", 2.0, "Goal y in the global frame (m)", min_value=-50.0, max_value=50.0)
        self.add_post_set_parameters_callback(self._on_params_set)
        self._rng = random.Random()
        self._nearest = math.inf
        self._last_scan = 0.0
        self._plans = 0
        self.get_logger().info("created (unconfigured)")

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Subscribe to scans and create the plan publisher."""
        self.own_subscription(LaserScan, "scan", self._on_scan, qos_profile_sensor_data)
        self._pub = self.own_publisher(Path, "plan", 10)
        self.get_logger().info(
            f"configured: planning in {self.param('global_frame')} from "
            f"{self.resolve_topic_name('scan')} to {self.resolve_topic_name('plan')}, "
            f"tolerance {self.param('tolerance_m')} m"
        )
        return SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Start replanning."""
        result = super().on_activate(state)
        self.start_ticking()
        self.get_logger().info(
            f"activated: replanning at {self.param('planner_frequency_hz')} Hz towards "
            f"({self.param('goal_x')}, {self.param('goal_y')})"
        )
        return result

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Stop replanning."""
        self.stop_ticking()
        self.get_logger().info(f"deactivated: stopped after {self._plans} plans")
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Drop the subscription, the publisher and the obstacle data."""
        count = self.release()
        self._pub = self._timer = None
        self._nearest, self._last_scan = math.inf, 0.0
        self.get_logger().info(f"cleaned up: released {count} entities")
        return SUCCESS

    def _on_scan(self, msg: LaserScan) -> None:
        ranges = np.frombuffer(msg.ranges, dtype=np.float32)
        valid = ranges[(ranges >= msg.range_min) & (ranges <= msg.range_max)]
        self._nearest = float(valid.min()) if valid.size else math.inf
        self._last_scan = time.monotonic()

    def tick(self) -> None:
        """Plan once."""
        if self._pub is None:
            return
        log = self.get_logger()
        age = time.monotonic() - self._last_scan
        if age > SCAN_TIMEOUT_S:
            log.warn(
                "no scan received yet" if self._last_scan == 0.0 else f"last scan is {age:.1f} s old",
                throttle_duration_sec=10.0,
            )
            log.warn("planning without obstacle data", throttle_duration_sec=10.0)
        elif self._nearest < self.param("tolerance_m"):
            log.error(
                f"obstacle at {self._nearest:.2f} m is inside the tolerance "
                f"{self.param('tolerance_m')} m: no valid plan",
                throttle_duration_sec=5.0,
            )
            return
        gx, gy = self.param("goal_x"), self.param("goal_y")
        if self._rng.random() < 1.0 / 60.0:
            log.error(f"planning failed: goal ({gx:.1f}, {gy:.1f}) unreachable (simulated)")
            return
        path = Path()
        path.header.stamp = self.get_clock().now().to_msg()
        path.header.frame_id = self.param("global_frame")
        steps = 20
        bend = 0.5 * math.sin(time.monotonic() / 10.0)
        length, prev = 0.0, (0.0, 0.0)
        for i in range(steps + 1):
            s = i / steps
            x = gx * s - gy * bend * math.sin(math.pi * s) * 0.2
            y = gy * s + gx * bend * math.sin(math.pi * s) * 0.2
            pose = PoseStamped()
            pose.header = path.header
            pose.pose.position.x, pose.pose.position.y = x, y
            pose.pose.orientation.w = 1.0
            path.poses.append(pose)
            length += math.hypot(x - prev[0], y - prev[1])
            prev = (x, y)
        self._pub.publish(path)
        self._plans += 1
        log.debug(
            f"plan #{self._plans}: {len(path.poses)} poses, {length:.2f} m, nearest obstacle {self._nearest:.2f} m",
            throttle_duration_sec=5.0,
        )
