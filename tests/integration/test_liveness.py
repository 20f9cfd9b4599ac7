"""A robot process that stops answering (its host's link down, or frozen) shows its nodes
unreachable within 5 s, not after the DDS lease (20+ s), and they come back when it answers.
SIGSTOP stands in for the cut link here: the process keeps its place in the DDS graph and
answers nothing (tests/integration/test_networks.py cuts real links between namespaces)."""
from __future__ import annotations

import signal
import time

import pytest

from lifecycle_site.fleet.models import ManagedNode
from tests import stack
from tests.integration.conftest import register, transition, wait_node

ROBOT, OTHER = "live-agv", "live-arm"
BOUND_S = 5.0


@pytest.fixture(scope="module")
def robots(live_db, gateway):
    register(ROBOT, stack.domain(25))
    register(OTHER, stack.domain(26))
    processes = {
        ROBOT: stack.start_robot("live-agv-nodes", stack.domain(25), "lidar_driver,camera_driver"),
        OTHER: stack.start_robot("live-arm-nodes", stack.domain(26), "lidar_driver"),
    }
    for key in (f"{ROBOT}.lidar_driver", f"{ROBOT}.camera_driver", f"{OTHER}.lidar_driver"):
        wait_node(None, key, alive=True, state="unconfigured", timeout=30)
    yield processes
    for process in processes.values():
        process.popen.send_signal(signal.SIGCONT)
        process.stop()


def test_a_process_that_stops_answering_is_unreachable_within_five_seconds(api, robots):
    frozen = robots[ROBOT]
    frozen.popen.send_signal(signal.SIGSTOP)
    stopped = time.monotonic()
    try:
        for node in ("lidar_driver", "camera_driver"):
            wait_node(api, f"{ROBOT}.{node}", alive=False, timeout=BOUND_S + 1)
        took = time.monotonic() - stopped
        node = api.get(f"/api/v1/nodes/{ROBOT}.lidar_driver").json()
        assert (node["alive"], node["gone_reason"]) == (False, "unreachable"), node
        print(f"[liveness] a frozen robot process shown unreachable after {took:.2f} s")
        assert took < BOUND_S, f"unreachable after {took:.1f} s"
        # The other robot's nodes stay alive and take commands.
        assert ManagedNode.objects.get(key=f"{OTHER}.lidar_driver").alive
        assert transition(api, f"{OTHER}.lidar_driver", "configure").status_code == 200
        response = transition(api, f"{ROBOT}.lidar_driver", "configure")
        assert response.status_code in (404, 409, 503), response.json()
    finally:
        frozen.popen.send_signal(signal.SIGCONT)
    resumed = time.monotonic()
    for node in ("lidar_driver", "camera_driver"):
        wait_node(api, f"{ROBOT}.{node}", alive=True, state="unconfigured", timeout=BOUND_S + 1)
    print(f"[liveness] back after {time.monotonic() - resumed:.2f} s")
    assert api.get(f"/api/v1/nodes/{ROBOT}.lidar_driver").json()["gone_reason"] == ""
    assert transition(api, f"{ROBOT}.camera_driver", "configure").status_code == 200
    wait_node(api, f"{ROBOT}.camera_driver", alive=True, state="inactive")


def test_editing_a_robot_without_moving_its_nodes_keeps_them_alive(api, robots):
    from lifecycle_site.fleet.models import Robot

    robot = Robot.objects.get(name=OTHER)
    robot.auto_recover = not robot.auto_recover
    robot.save()  # the site publishes the gateway's new configuration
    ends = time.monotonic() + 6  # three configuration reads of the gateway
    while time.monotonic() < ends:
        assert ManagedNode.objects.get(key=f"{OTHER}.lidar_driver").alive, "the edit made the node flap lost"
        time.sleep(0.1)
