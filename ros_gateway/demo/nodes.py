"""Registry of the demo robot nodes (the classes live in the sibling modules)."""

from __future__ import annotations

from typing import Any

from .flaky import FAILURE_MODES, FlakyNode
from .generic import GenericNode
from .planning import Planner
from .sensors import CameraDriver, LidarDriver
from .teleop import Joystick, JoyToVel

#: node name -> class; every class takes ``(node_name, **rclpy Node kwargs)``.
NODE_CLASSES: dict[str, type[Any]] = {
    "joy_to_vel": JoyToVel,
    "joystick": Joystick,
    "lidar_driver": LidarDriver,
    "camera_driver": CameraDriver,
    "planner": Planner,
    "flaky_node": FlakyNode,
}

#: nodes started when ``--nodes`` is not given
DEFAULT_NODES: tuple[str, ...] = tuple(NODE_CLASSES)

#: node names that are plain rclpy nodes (no lifecycle interface)
PLAIN_NODES: frozenset[str] = frozenset({"joystick"})

__all__ = [
    "CameraDriver",
    "DEFAULT_NODES",
    "FAILURE_MODES",
    "FlakyNode",
    "GenericNode",
    "JoyToVel",
    "Joystick",
    "LidarDriver",
    "NODE_CLASSES",
    "PLAIN_NODES",
    "Planner",
]
