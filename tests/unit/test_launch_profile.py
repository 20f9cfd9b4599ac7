"""A launch profile read from the site's configuration: every field checked, a malformed one named."""
from __future__ import annotations

import math
import signal

import pytest

from ros_gateway.launch_profile import LaunchProfile

ROBOT = "agv-1"


def test_from_config_reads_the_site_json():
    profile = LaunchProfile.from_config(ROBOT, {
        "name": "nav2.bringup", "command": "ros2", "args": ["launch", "nav2_bringup", "x.launch.py"],
        "env": {"ROS_DOMAIN_ID": "7", "A": ""}, "cwd": "/opt", "respawn": False, "respawn_delay": 2,
        "stop_signal": "SIGINT", "stop_grace": 15, "max_failures": 3, "failure_window": 60.5})
    assert profile == LaunchProfile(ROBOT, "nav2.bringup", "ros2", ("launch", "nav2_bringup", "x.launch.py"),
                                    (("A", ""), ("ROS_DOMAIN_ID", "7")), "/opt", False, 2.0, signal.SIGINT, 15.0, 3,
                                    60.5)
    assert LaunchProfile.from_config(ROBOT, {"name": "a", "command": "b", "env": None}) == LaunchProfile(ROBOT, "a",
                                                                                                          "b")


@pytest.mark.parametrize("data, field", [
    (["name", "cmd"], "JSON object"),
    ({"command": "x"}, "name"),
    ({"name": "has space", "command": "x"}, "name"),
    ({"name": "n" * 65, "command": "x"}, "name"),
    ({"name": "n", "command": ""}, "command"),
    ({"name": "n", "command": "a\0b"}, "command"),
    ({"name": "n", "command": "x" * 4097}, "command"),
    ({"name": "n", "command": "x", "args": "--fast"}, "args"),
    ({"name": "n", "command": "x", "args": ["a"] * 257}, "args"),
    ({"name": "n", "command": "x", "args": ["ok", 3]}, r"args\[1\]"),
    ({"name": "n", "command": "x", "env": ["A=1"]}, "env"),
    ({"name": "n", "command": "x", "env": {"A": 1}}, "env"),
    ({"name": "n", "command": "x", "env": {f"K{n}": "v" for n in range(257)}}, "env"),
    ({"name": "n", "command": "x", "env": {"A=B": "v"}}, "env"),
    ({"name": "n", "command": "x", "cwd": ""}, "cwd"),
    ({"name": "n", "command": "x", "respawn": "yes"}, "respawn"),
    ({"name": "n", "command": "x", "respawn_delay": -1}, "respawn_delay"),
    ({"name": "n", "command": "x", "respawn_delay": math.inf}, "respawn_delay"),
    ({"name": "n", "command": "x", "respawn_delay": math.nan}, "respawn_delay"),
    ({"name": "n", "command": "x", "respawn_delay": 301}, "respawn_delay"),
    ({"name": "n", "command": "x", "respawn_delay": True}, "respawn_delay"),
    ({"name": "n", "command": "x", "stop_grace": 300.5}, "stop_grace"),
    ({"name": "n", "command": "x", "stop_grace": "10"}, "stop_grace"),
    ({"name": "n", "command": "x", "stop_signal": "SIGKILL"}, "stop_signal"),
    ({"name": "n", "command": "x", "stop_signal": 15}, "stop_signal"),
    ({"name": "n", "command": "x", "max_failures": 0}, "max_failures"),
    ({"name": "n", "command": "x", "max_failures": 2.5}, "max_failures"),
    ({"name": "n", "command": "x", "failure_window": 10 ** 400}, "failure_window"),
])
def test_from_config_refuses_what_is_malformed_naming_the_field(data, field):
    with pytest.raises(ValueError, match=field):
        LaunchProfile.from_config(ROBOT, data)
