"""Desired states kept against other tools, on real nodes: with "alert" a change by another tool
raises an alert; with "enforce" the gateway drives the node back (source recovery); and against a
competing manager (a process of the test that activates the node every second, as a team's own
bring-up script would) it gives up after a few rounds, says so (the node, the alert, the
attention strip) and leaves the node alone until an operator resumes it. Nothing loops."""
from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from lifecycle_site.alerts.models import Alert
from lifecycle_site.fleet.models import GroupRun, ManagedNode, Robot
from ros_gateway.desired_keeper import FIGHT_LIMIT
from tests import stack
from tests.integration.conftest import register, transition, wait_node

ROBOT = "it-keep"
DOMAIN_OFFSET = 42
HERE = Path(__file__).resolve().parent
RULE = "Desired state not kept"  # one of the rules every installation has (alerts/installed_rules.py)


@pytest.fixture(scope="module")
def robot(gateway):
    register(ROBOT, stack.domain(DOMAIN_OFFSET))
    process = stack.start_robot("keep-main", stack.domain(DOMAIN_OFFSET), "lidar_driver,camera_driver")
    for name in ("lidar_driver", "camera_driver"):
        wait_node(None, f"{ROBOT}.{name}", alive=True, state="unconfigured")
    yield process
    process.stop()
    Robot.objects.filter(name=ROBOT).update(enabled=False)  # its nodes' policies end with it


def keep(api, node: str, **body):
    answer = api.put(f"/api/v1/nodes/{ROBOT}.{node}/desired-state", body, content_type="application/json")
    assert answer.status_code == 200, answer.json()
    return answer.json()


def external(node: str, transition_id: int) -> None:
    """Another tool's change (its own rclpy process): 3 activate, 4 deactivate."""
    done = subprocess.run([sys.executable, str(HERE / "ros_call.py"), str(stack.domain(DOMAIN_OFFSET)), f"/{node}",
                           str(transition_id)], capture_output=True, text=True, timeout=60, env=stack.environment())
    assert "success" in done.stdout, done.stdout + done.stderr


def recoveries(node: str) -> int:
    return GroupRun.objects.filter(robot__name=ROBOT, operation="recover", only_nodes=[f"/{node}"]).count()


def test_alert_raises_an_alert_and_enforce_drives_the_node_back(api, robot):
    for node in ("lidar_driver", "camera_driver"):
        for label in ("configure", "activate"):
            assert transition(api, f"{ROBOT}.{node}", label).status_code == 200
    assert keep(api, "lidar_driver", desired_state="active", keep="alert")["keep"] == "alert"
    assert keep(api, "camera_driver", desired_state="active", keep="enforce")["keep"] == "enforce"
    time.sleep(1.5)  # the gateway's config follows (published on commit)

    external("lidar_driver", 4)
    fired = stack.wait_for(lambda: Alert.objects.filter(rule_name=RULE, subject=f"{ROBOT}.lidar_driver",
                                                        status=Alert.Status.FIRING).first(), 20, "the alert")
    assert "was moved to inactive; its desired state is active, kept against other tools" in fired.summary
    wait_node(None, f"{ROBOT}.lidar_driver", state="inactive")  # "alert" only: left where it is
    assert recoveries("lidar_driver") == 0

    external("camera_driver", 4)
    wait_node(None, f"{ROBOT}.camera_driver", timeout=20, state="active")  # driven back
    run = GroupRun.objects.filter(robot__name=ROBOT, operation="recover", only_nodes=["/camera_driver"]).get()
    stack.wait_for(lambda: GroupRun.objects.get(pk=run.pk).status == "succeeded", 10, "the run's end")
    assert run.source == "recovery"


def test_against_a_competing_manager_it_stops_says_so_and_resumes_only_when_told(api, robot):
    # The lidar, never driven back so far (undone changes count per node, within FIGHT_WINDOW_S).
    node, key = "lidar_driver", f"{ROBOT}.lidar_driver"
    before = recoveries(node)
    keep(api, node, desired_state="inactive", keep="enforce")
    time.sleep(1.5)
    assert transition(api, key, "activate").status_code == 200  # ours, away from its desired state
    time.sleep(3)  # (past the grace)
    assert ManagedNode.objects.get(key=key).state_label == "active" and recoveries(node) == before  # not undone
    assert transition(api, key, "deactivate").status_code == 200
    rival = stack.Process("competing-manager", [sys.executable, str(HERE / "competing_manager.py"),
                                                str(stack.domain(DOMAIN_OFFSET)), f"/{node}", "90"],
                          stack.environment(), stack.log_dir())
    try:
        stopped = stack.wait_for(lambda: ManagedNode.objects.filter(key=key, enforcement_stopped__isnull=False)
                                 .first(), 60, "the gateway to give up")
        assert f"another manager keeps changing /{node}" in stopped.enforcement_note
        assert "last change by an external tool at" in stopped.enforcement_note
        assert recoveries(node) - before == FIGHT_LIMIT
        # Left alone: the rival keeps it active, and nothing more is sent.
        time.sleep(6)
        assert recoveries(node) - before == FIGHT_LIMIT
        assert ManagedNode.objects.get(key=key).state_label == "active"
        assert ManagedNode.objects.select_related("robot").get(key=key).keep == "paused"
        alert = stack.wait_for(lambda: Alert.objects.filter(rule_name=RULE, subject=key,
                                                            status=Alert.Status.FIRING).first(), 20, "the alert")
        assert "another manager keeps changing" in alert.summary
        page = api.get("/").content.decode()
        assert "another manager keeps changing it" in page
    finally:
        rival.stop()
    # An operator resumes it: the gateway takes it back to its desired state, and keeps it there.
    answer = keep(api, node, resume=True)
    assert (answer["keep"], answer["enforcement_stopped"]) == ("enforce", None)
    wait_node(None, key, timeout=20, state="inactive")
    external(node, 3)
    wait_node(None, key, timeout=20, state="inactive")
    assert recoveries(node) - before == FIGHT_LIMIT + 2
