"""Teleoperation demo nodes: a simulated joystick and a joy -> cmd_vel converter."""

from __future__ import annotations

import math
import time
from typing import Any, Optional

from geometry_msgs.msg import Twist
from rclpy.node import Node
from sensor_msgs.msg import Joy

from .base import SUCCESS, LifecycleState, PeriodicNode, TransitionCallbackReturn, declare_parameter

JOY_AXES = 8
JOY_BUTTONS = 12


class JoyToVel(PeriodicNode):
    """Lifecycle teleop node (like teleop_twist_joy): ``joy`` (Joy) -> ``cmd_vel`` (Twist).

    While active it publishes at ``publish_rate_hz`` the scaled stick axes when the deadman
    button is held, zero velocity once when it is released, and warns when the joystick has
    been silent for longer than ``joy_timeout_s``.
    """

    RATE_PARAMETER, RATE_NAME = "publish_rate_hz", "publish rate"

    def __init__(self, node_name: str = "joy_to_vel", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.declare(
            "scale_linear", 0.5, "Linear velocity (m/s) at full stick deflection", min_value=0.0, max_value=2.0
        )
        self.declare("scale_angular", 1.0, "Angular velocity (rad/s) at full deflection", min_value=0.0, max_value=3.0)
        self.declare("axis_linear", 1, "Joy axis index driving linear.x", min_value=0, max_value=JOY_AXES - 1)
        self.declare("axis_angular", 0, "Joy axis index driving angular.z", min_value=0, max_value=JOY_AXES - 1)
        self.declare(
            "deadman_button", 4, "Joy button that must be held to move", min_value=0, max_value=JOY_BUTTONS - 1
        )
        self.declare("publish_rate_hz", 10.0, "cmd_vel publish rate while active", min_value=1.0, max_value=50.0)
        self.declare(
            "joy_timeout_s", 1.0, "Joystick silence (s) after which the robot stops", min_value=0.1, max_value=10.0
        )
        self.add_post_set_parameters_callback(self._on_params_set)
        self._last_joy: Optional[Joy] = None
        self._last_joy_time = 0.0
        self._active_since = 0.0
        self._stale = False
        self._deadman = False
        self._published = 0
        self.get_logger().info("created (unconfigured)")

    # -- transitions ------------------------------------------------------------------
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Create the cmd_vel publisher and the joy subscription."""
        self._pub = self.own_publisher(Twist, "cmd_vel", 10)
        self.own_subscription(Joy, "joy", self._on_joy, 10)
        self.get_logger().info(
            f"configured: {self.resolve_topic_name('joy')} -> "
            f"{self.resolve_topic_name('cmd_vel')}, deadman button "
            f"{self.param('deadman_button')}, scales {self.param('scale_linear')} m/s / "
            f"{self.param('scale_angular')} rad/s"
        )
        return SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Enable the publisher and start the publish timer."""
        result = super().on_activate(state)
        self._active_since = time.monotonic()
        self._stale = False
        self._deadman = False
        self.start_ticking()
        self.get_logger().info(f"activated: publishing cmd_vel at {self.param('publish_rate_hz')} Hz")
        return result

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Stop the robot (one zero Twist), stop the timer, disable the publisher."""
        if self._pub is not None:
            self._pub.publish(Twist())
        self.stop_ticking()
        self.get_logger().info(f"deactivated: sent zero velocity, stopped publishing after {self._published} messages")
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Destroy publisher and subscription."""
        count = self.release()
        self._pub = self._timer = self._last_joy = None
        self.get_logger().info(f"cleaned up: released {count} entities")
        return SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Send a last zero Twist when shutting down from active, then release."""
        if state.label == "active" and self._pub is not None:
            self._pub.publish(Twist())
            self.get_logger().info("shutdown while active: sent zero velocity")
        return super().on_shutdown(state)

    # -- runtime ----------------------------------------------------------------------
    def _on_joy(self, msg: Joy) -> None:
        now = time.monotonic()
        if self._stale and self.state_label == "active":
            since = max(self._last_joy_time, self._active_since)
            self.get_logger().info(f"joystick back after {now - since:.1f} s of silence")
        self._stale = False
        self._last_joy = msg
        self._last_joy_time = now

    def tick(self) -> None:
        if self._pub is None:
            return
        log = self.get_logger()
        now = time.monotonic()
        age = now - self._last_joy_time
        if now - max(self._last_joy_time, self._active_since) > self.param("joy_timeout_s"):
            if not self._stale:
                self._pub.publish(Twist())
                self._stale = True
            silence = "no joystick message yet" if self._last_joy is None else (f"no joystick message for {age:.1f} s")
            log.warn(f"{silence}: holding zero velocity", throttle_duration_sec=5.0)
            return
        if self._last_joy is None:
            return
        joy = self._last_joy
        button = self.param("deadman_button")
        pressed = button < len(joy.buttons) and joy.buttons[button] == 1
        if pressed != self._deadman:
            self._deadman = pressed
            log.info(f"deadman button {button} " + ("pressed: teleop enabled" if pressed else "released: stopping"))
            if not pressed:
                self._pub.publish(Twist())
                self._published += 1
        if not pressed:
            return
        ax_lin, ax_ang = self.param("axis_linear"), self.param("axis_angular")
        if max(ax_lin, ax_ang) >= len(joy.axes):
            log.error(
                f"axis index {max(ax_lin, ax_ang)} out of range: Joy message has only "
                f"{len(joy.axes)} axes; publishing zero velocity",
                throttle_duration_sec=5.0,
            )
            self._pub.publish(Twist())
            return
        twist = Twist()
        twist.linear.x = self.param("scale_linear") * joy.axes[ax_lin]
        twist.angular.z = self.param("scale_angular") * joy.axes[ax_ang]
        self._pub.publish(twist)
        self._published += 1
        log.debug(
            f"cmd_vel linear.x={twist.linear.x:+.2f} angular.z={twist.angular.z:+.2f} "
            f"(joy age {age * 1000:.0f} ms, {self._published} sent)",
            throttle_duration_sec=5.0,
        )


class Joystick(Node):
    """Plain (non-lifecycle) node publishing a simulated gamepad on ``joy``.

    Sticks follow slow sine waves; the deadman button (4) is held except for a few seconds
    every ``deadman_cycle_s``; every ``dropout_interval_s`` the radio drops out briefly.
    """

    def __init__(self, node_name: str = "joystick", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        declare_parameter(self, "rate_hz", 10.0, "Joy publish rate", min_value=1.0, max_value=50.0)
        declare_parameter(self, "deadman_button", 4, "Button simulated as held", min_value=0, max_value=JOY_BUTTONS - 1)
        declare_parameter(
            self,
            "deadman_cycle_s",
            30.0,
            "Period of the simulated release of the deadman button (3 s)",
            min_value=5.0,
            max_value=600.0,
        )
        declare_parameter(
            self,
            "dropout_interval_s",
            60.0,
            "Period of simulated 1.5 s radio dropouts (0 = never)",
            min_value=0.0,
            max_value=3600.0,
        )
        self.add_post_set_parameters_callback(self._on_params_set)
        self._pub = self.create_publisher(Joy, "joy", 10)
        self._start = time.monotonic()
        self._count = 0
        self._held = True
        self._in_dropout = False
        self._next_dropout = self._start + (self.get_parameter("dropout_interval_s").value or math.inf)
        self._timer = self.create_timer(1.0 / self.get_parameter("rate_hz").value, self._tick)
        self.get_logger().info(
            f"simulated joystick publishing on {self.resolve_topic_name('joy')} at "
            f"{self.get_parameter('rate_hz').value} Hz"
        )

    def _on_params_set(self, params: list) -> None:
        for p in params:
            if p.name == "rate_hz":
                self.destroy_timer(self._timer)
                self._timer = self.create_timer(1.0 / p.value, self._tick)
                self.get_logger().info(f"joy rate now {p.value} Hz")
            elif p.name == "dropout_interval_s":
                self._next_dropout = time.monotonic() + (p.value or math.inf)

    def _tick(self) -> None:
        now = time.monotonic()
        t = now - self._start
        log = self.get_logger()
        if now >= self._next_dropout:
            if not self._in_dropout:
                self._in_dropout = True
                log.warn("simulated radio dropout: joystick silent for 1.5 s")
            if now < self._next_dropout + 1.5:
                return
            self._in_dropout = False
            self._next_dropout = now + (self.get_parameter("dropout_interval_s").value or math.inf)
            log.info("radio link restored")
        cycle = self.get_parameter("deadman_cycle_s").value
        held = (t % cycle) < cycle - 3.0
        if held != self._held:
            self._held = held
            log.info("operator " + ("pressed" if held else "released") + " the deadman button")
        msg = Joy()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = "joy"
        axes = [0.0] * JOY_AXES
        axes[0] = 0.6 * math.sin(2 * math.pi * t / 7.0)
        axes[1] = 0.9 * math.sin(2 * math.pi * t / 11.0)
        axes[3] = 0.3 * math.sin(2 * math.pi * t / 5.0)
        msg.axes = axes
        buttons = [0] * JOY_BUTTONS
        buttons[self.get_parameter("deadman_button").value] = 1 if held else 0
        msg.buttons = buttons
        self._pub.publish(msg)
        self._count += 1
        log.debug(
            f"joy #{self._count}: axes[0]={axes[0]:+.2f} axes[1]={axes[1]:+.2f} "
            f"deadman={'held' if held else 'released'}",
            throttle_duration_sec=5.0,
        )
