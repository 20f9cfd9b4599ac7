"""Simulated sensor drivers: a 2D lidar and a small monochrome camera."""

from __future__ import annotations

import array
import math
import random
import time
from typing import Any, Optional

import numpy as np
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Image, LaserScan

from .base import SUCCESS, LifecycleState, PeriodicNode, TransitionCallbackReturn
from .diagnostics import ERROR, OK, WARN, EventWindow, Report, StatusPublisher

SCAN_RATE_TOLERANCE = 0.1  # diagnostic_updater's FrequencyStatus default: +-10 %
DROPPED_POINTS_WARN = 10  # points lost within the window above which the scan status warns


def room_ranges(
    angles: np.ndarray, half_x: float = 4.0, half_y: float = 2.5, offset: tuple[float, float] = (0.8, -0.4)
) -> np.ndarray:
    """Ranges from a point `offset` inside a rectangular room to its walls, plus a pillar."""
    ox, oy = offset
    cos, sin = np.cos(angles), np.sin(angles)
    with np.errstate(divide="ignore", invalid="ignore"):
        tx = np.where(cos > 0, (half_x - ox) / cos, (-half_x - ox) / cos)
        ty = np.where(sin > 0, (half_y - oy) / sin, (-half_y - oy) / sin)
    ranges = np.minimum(np.abs(tx), np.abs(ty))
    # a round pillar of radius 0.3 m at (1.5, 1.0) relative to the sensor
    px, py, radius = 1.5, 1.0, 0.3
    proj = cos * px + sin * py
    disc = proj**2 - (px * px + py * py - radius * radius)
    hit = (disc > 0) & (proj > 0)
    pillar = np.where(hit, proj - np.sqrt(np.where(hit, disc, 0.0)), np.inf)
    return np.minimum(ranges, pillar).astype(np.float32)


class LidarDriver(PeriodicNode):
    """Lifecycle 2D lidar driver publishing synthetic ``scan`` (LaserScan) while active."""

    RATE_PARAMETER, RATE_NAME = "scan_rate_hz", "scan rate"

    def __init__(self, node_name: str = "lidar_driver", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.declare("frame_id", "laser", "TF frame of the scans", read_only=True)
        self.declare("scan_rate_hz", 5.0, "Scan publish rate while active", min_value=1.0, max_value=40.0)
        self.declare("range_min", 0.12, "Minimum valid range (m)", min_value=0.0, max_value=1.0)
        self.declare("range_max", 12.0, "Maximum valid range (m)", min_value=1.0, max_value=100.0)
        self.declare("num_points", 360, "Points per scan (applied on configure)", min_value=90, max_value=2000)
        self.declare(
            "drop_probability", 0.01, "Probability per scan of a simulated packet loss", min_value=0.0, max_value=1.0
        )
        self.add_post_set_parameters_callback(self._on_params_set)
        self._rng = random.Random()
        self._base: Optional[np.ndarray] = None
        self._scans = 0
        self._scan_times = EventWindow()
        self._dropped = EventWindow()
        self._discarded = 0
        self.diagnostics = StatusPublisher(
            self, "sim_lidar_2d", {"Scan rate": self._scan_status}, alive=lambda: self.state_label != "finalized"
        )
        self.get_logger().info("created (unconfigured)")

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Precompute the synthetic room and create the scan publisher."""
        n = self.param("num_points")
        angles = np.linspace(-math.pi, math.pi, n, endpoint=False)
        self._base = room_ranges(angles)
        self._pub = self.own_publisher(LaserScan, "scan", qos_profile_sensor_data)
        self.get_logger().info(
            f"configured: {n} points per scan, frame {self.param('frame_id')}, range "
            f"{self.param('range_min')}..{self.param('range_max')} m on "
            f"{self.resolve_topic_name('scan')}"
        )
        return SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Spin up the (simulated) motor and start publishing."""
        result = super().on_activate(state)
        self.start_ticking()
        self.get_logger().info(f"activated: motor spinning, publishing at {self.param('scan_rate_hz')} Hz")
        return result

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Stop publishing and spin down."""
        self.stop_ticking()
        self.get_logger().info(f"deactivated: motor stopped after {self._scans} scans")
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Release the publisher and the precomputed room."""
        count = self.release()
        self._pub = self._timer = self._base = None
        self.get_logger().info(f"cleaned up: released {count} entities")
        return SUCCESS

    def tick(self) -> None:
        if self._pub is None or self._base is None:
            return
        log = self.get_logger()
        rng = self._rng
        if rng.random() < 0.002:
            log.error("scan packet checksum mismatch: frame discarded (simulated)")
            self._discarded += 1
            return
        n = len(self._base)
        ranges = self._base + np.float32(rng.gauss(0.0, 0.01))
        ranges = ranges + (np.arange(n, dtype=np.float32) % 7 - 3) * np.float32(0.002)
        ranges[(ranges > self.param("range_max")) | (ranges < self.param("range_min"))] = np.inf
        if rng.random() < self.param("drop_probability"):
            dropped = rng.randint(3, max(4, n // 20))
            start = rng.randrange(n)
            idx = (np.arange(dropped) + start) % n
            ranges[idx] = np.nan
            self._dropped.add(dropped)
            log.warn(f"dropped {dropped} points (simulated packet loss)")
        msg = LaserScan()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.param("frame_id")
        msg.angle_min = -math.pi
        msg.angle_increment = 2 * math.pi / n
        msg.angle_max = msg.angle_min + msg.angle_increment * (n - 1)
        rate = self.param("scan_rate_hz")
        msg.scan_time = 1.0 / rate
        msg.time_increment = msg.scan_time / n
        msg.range_min = self.param("range_min")
        msg.range_max = self.param("range_max")
        msg.ranges = array.array("f", ranges.tobytes())
        self._pub.publish(msg)
        self._scans += 1
        self._scan_times.add()
        log.debug(
            f"scan #{self._scans}: {n} points, nearest {float(np.nanmin(ranges)):.2f} m", throttle_duration_sec=5.0
        )

    def start_ticking(self) -> None:
        # a new rate (or a fresh activation) starts a new measurement window
        super().start_ticking()
        self._scan_times.restart()
        self._dropped.restart()

    def _scan_status(self) -> Report:
        """Scan rate against ``scan_rate_hz`` and points lost in the last window."""
        now = time.monotonic()
        expected = float(self.param("scan_rate_hz"))
        values: dict[str, Any] = {
            "frequency_hz": 0.0,
            "expected_hz": expected,
            "tolerance_pct": SCAN_RATE_TOLERANCE * 100,
            "dropped_points": 0,
            "dropped_points_warn": DROPPED_POINTS_WARN,
            "discarded_scans": self._discarded,
            "scans": self._scans,
            "state": self.state_label,
        }
        if self.state_label != "active":
            # Not publishing is commanded (the lifecycle manager keeps the driver inactive), not a
            # fault: like a diagnostic_updater driver that reports OK while idle, so that an idle
            # robot does not show up yellow in the aggregate. The lifecycle state tells the rest.
            return OK, f"not active ({self.state_label}): not publishing scans", values
        frequency = self._scan_times.frequency(now)
        last = self._scan_times.last(now)
        silent = now - (last if last is not None else self._scan_times.since)
        dropped = int(self._dropped.total(now))
        values.update(frequency_hz=frequency, dropped_points=dropped)
        level, problems = OK, []
        # the interval estimate cannot see a silence (FrequencyStatus: "No events recorded")
        if silent > max(3.0 / expected, 1.0):
            values["frequency_hz"] = 0.0
            level, problems = ERROR, [f"no scan for {silent:.1f} s"]
        elif frequency and frequency < expected * (1 - SCAN_RATE_TOLERANCE):
            level, problems = WARN, ["scan rate too low"]
        elif frequency > expected * (1 + SCAN_RATE_TOLERANCE):
            level, problems = WARN, ["scan rate too high"]
        if dropped > DROPPED_POINTS_WARN:
            level = max(level, WARN)
            problems.append(f"{dropped} points dropped in {self._dropped.window_s:.0f} s")
        if problems:
            return level, "; ".join(problems), values
        return OK, f"scanning at {frequency:.1f} Hz" if frequency else "starting to scan", values


class CameraDriver(PeriodicNode):
    """Lifecycle camera driver publishing a moving mono8 test pattern on ``image_raw``."""

    RATE_PARAMETER, RATE_NAME, RATE_UNIT = "fps", "frame rate", "fps"

    def __init__(self, node_name: str = "camera_driver", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.declare("frame_id", "camera_optical", "TF frame of the images", read_only=True)
        self.declare("fps", 5.0, "Frames per second while active", min_value=1.0, max_value=60.0)
        self.declare("width", 64, "Image width in pixels (applied on configure)", min_value=16, max_value=640)
        self.declare("height", 48, "Image height in pixels (applied on configure)", min_value=16, max_value=480)
        self.declare("exposure_ms", 10.0, "Exposure time; above 1000/fps frames drop", min_value=0.1, max_value=1000.0)
        self.add_post_set_parameters_callback(self._on_params_set)
        self._rng = random.Random()
        self._pattern: Optional[np.ndarray] = None
        self._frames = 0
        self.get_logger().info("created (unconfigured)")

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Open the (simulated) device at the configured resolution."""
        w, h = self.param("width"), self.param("height")
        xx, yy = np.meshgrid(np.arange(w), np.arange(h))
        self._pattern = (xx * 4 + yy * 2).astype(np.int32)
        self._pub = self.own_publisher(Image, "image_raw", qos_profile_sensor_data)
        self.get_logger().info(
            f"configured: {w}x{h} mono8 on {self.resolve_topic_name('image_raw')}, "
            f"exposure {self.param('exposure_ms')} ms"
        )
        self._check_exposure()
        return SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Start streaming."""
        result = super().on_activate(state)
        self.start_ticking()
        self.get_logger().info(f"activated: streaming at {self.param('fps')} fps")
        return result

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Stop streaming."""
        self.stop_ticking()
        self.get_logger().info(f"deactivated: stream stopped after {self._frames} frames")
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Close the device."""
        count = self.release()
        self._pub = self._timer = self._pattern = None
        self.get_logger().info(f"cleaned up: device closed, released {count} entities")
        return SUCCESS

    def _check_exposure(self) -> None:
        period_ms = 1000.0 / self.param("fps")
        if self.param("exposure_ms") > period_ms:
            self.get_logger().warn(
                f"exposure {self.param('exposure_ms')} ms exceeds the frame period "
                f"{period_ms:.1f} ms: frames will be dropped"
            )

    def _on_params_set(self, params: list) -> None:
        if {p.name for p in params} & {"fps", "exposure_ms"}:
            self._check_exposure()
        super()._on_params_set(params)

    def tick(self) -> None:
        if self._pub is None or self._pattern is None:
            return
        log = self.get_logger()
        rng = self._rng
        fps = self.param("fps")
        if rng.random() < 1.0 / (120.0 * fps):
            log.error("frame capture timeout: no frame from sensor within 2 frame periods")
            return
        if rng.random() < 1.0 / (40.0 * fps):
            log.warn(
                f"auto-exposure: scene too bright, exposure clamped at {self.param('exposure_ms')} ms (image saturated)"
            )
        h, w = self._pattern.shape
        msg = Image()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.param("frame_id")
        msg.height, msg.width = h, w
        msg.encoding = "mono8"
        msg.step = w
        msg.data = ((self._pattern + self._frames * 3) & 0xFF).astype(np.uint8).tobytes()
        self._pub.publish(msg)
        self._frames += 1
        log.debug(f"frame #{self._frames} {w}x{h}", throttle_duration_sec=5.0)
