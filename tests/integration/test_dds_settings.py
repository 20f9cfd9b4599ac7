"""A gateway's DDS settings live in its environment: checked at start with a clear error,
applied (the interfaces DDS may use become a Fast DDS profile), and reported to the site."""
from __future__ import annotations

import subprocess
import sys

import pytest
from django.core.management import call_command

from lifecycle_site.fleet.models import Gateway, Robot
from tests import stack
from tests.integration.conftest import register, transition, wait_node

NAME, ROBOT = "cell-lo", "lo-agv"


def gateway_env(tmp_path) -> dict[str, str]:
    path = tmp_path / f"{NAME}.env"
    call_command("add_gateway", NAME, env_file=str(path))
    return dict(line.split("=", 1) for line in path.read_text().splitlines() if line and not line.startswith("#"))


@pytest.fixture
def cell(live_db, ingest, tmp_path):
    env = gateway_env(tmp_path)
    register(ROBOT, stack.domain(29), gateway=NAME)
    processes = [stack.start_gateway(NAME, **env, LIFECYCLE_DDS_INTERFACES="lo"),
                 stack.start_robot("lo-agv-nodes", stack.domain(29), "lidar_driver")]
    yield processes[0]
    for process in processes:
        process.stop()
    Robot.objects.filter(name=ROBOT).delete()
    Gateway.objects.filter(name=NAME).delete()


def test_a_gateway_limited_to_one_interface_finds_its_robot_and_says_so(api, cell):
    wait_node(api, f"{ROBOT}.lidar_driver", alive=True, state="unconfigured", timeout=30)
    assert transition(api, f"{ROBOT}.lidar_driver", "configure").status_code == 200
    gateway = next(g for g in api.get("/api/v1/gateways").json()["gateways"] if g["name"] == NAME)
    assert gateway["dds"]["LIFECYCLE_DDS_INTERFACES"] == "127.0.0.1"
    assert "interfaces 127.0.0.1" in gateway["dds_summary"]
    assert "FASTRTPS_DEFAULT_PROFILES_FILE" not in gateway["dds"]  # ours, not the operator's


@pytest.mark.parametrize("setting, says", [
    ({"ROS_AUTOMATIC_DISCOVERY_RANGE": "LAN"}, "ROS_AUTOMATIC_DISCOVERY_RANGE='LAN': use one of"),
    ({"LIFECYCLE_DDS_INTERFACES": "eth9"}, "this host has no network interface 'eth9'"),
])
def test_a_gateway_with_unusable_dds_settings_stops_at_once_saying_why(live_db, setting, says):
    done = subprocess.run([sys.executable, "-m", "ros_gateway", "--name", "cell-bad"],
                          env=stack.environment(**setting), capture_output=True, text=True, timeout=30)
    assert done.returncode != 0
    assert says in done.stderr, done.stderr
