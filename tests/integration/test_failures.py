"""What goes wrong, for real: failing and raising callbacks, a slow node, nodes that vanish
and come back, robots added or disabled while running, garbage on the command queue,
and the gateway going away."""
from __future__ import annotations

import json

import pytest
import redis
from django.conf import settings

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import ManagedNode, Robot
from lifecycle_site.gateway_link import gateways
from ros_gateway.shared import protocol
from tests import stack
from tests.integration.conftest import register, transition, wait_node

ROBOT = "it-flaky"


@pytest.fixture(scope="module")
def flaky(gateway):
    register(ROBOT, stack.domain(3))
    modes = {
        "/fail": "fail_configure", "/raise": "raise_activate", "/errerr": "error_in_error", "/slow": "slow_configure",
    }
    processes = {
        ns: stack.start_robot(
            f"flaky{ns.replace('/', '-')}", stack.domain(3), "flaky_node",
            f"flaky_node.failure_mode:={mode}", "flaky_node.slow_seconds:=4.0", namespace=ns,
        )
        for ns, mode in modes.items()
    }
    yield processes
    for process in processes.values():
        process.stop()


def key(namespace: str) -> str:
    return f"{ROBOT}.{namespace.strip('/')}.flaky_node"


def test_failing_configure_is_422_with_the_nodes_reason(api, flaky):
    wait_node(api, key("/fail"), alive=True, state="unconfigured")
    response = transition(api, key("/fail"), "configure")
    assert response.status_code == 422, response.json()
    error = response.json()["error"]
    assert error["code"] == "transition_failed" and error["state"]["label"] == "unconfigured"
    assert "FAILURE" in error["message"] and "The node said:" in error["message"]
    record = TransitionRecord.objects.get(id=error["record_id"])
    outcome = (record.outcome, record.result_state_label, record.goal_state_label)
    assert outcome == ("failed", "unconfigured", "inactive")


def test_raising_activate_goes_through_error_processing_to_unconfigured(api, flaky):
    wait_node(api, key("/raise"), alive=True, state="unconfigured")
    assert transition(api, key("/raise"), "configure").status_code == 200
    response = transition(api, key("/raise"), "activate")
    assert response.status_code == 422
    error = response.json()["error"]
    assert error["state"]["label"] == "unconfigured" and "error processing" in error["message"]
    wait_node(api, key("/raise"), state="unconfigured")


def test_error_in_error_handling_finalizes_the_node(api, flaky):
    wait_node(api, key("/errerr"), alive=True, state="unconfigured")
    assert transition(api, key("/errerr"), "configure").status_code == 200
    response = transition(api, key("/errerr"), "activate")
    assert response.status_code == 422 and response.json()["error"]["state"]["label"] == "finalized"


def test_timeout_reports_504_then_the_late_transition_is_picked_up(api, flaky):
    wait_node(api, key("/slow"), alive=True, state="unconfigured")
    response = transition(api, key("/slow"), "configure", timeout=1)
    assert response.status_code == 504, response.json()
    error = response.json()["error"]
    assert error["code"] == "timeout" and "did not answer within 1 s" in error["message"]
    # The node was still busy, so the re-read could not tell yet; the state arrives later by event.
    assert error["state"] is None or error["state"]["label"] in ("configuring", "inactive")
    wait_node(api, key("/slow"), state="inactive", timeout=10)
    record = TransitionRecord.objects.get(id=error["record_id"])
    assert record.outcome == "timed_out" and record.source == "api"
    # The late completion of our own request is not mistaken for another tool's transition.
    assert not TransitionRecord.objects.filter(node__key=key("/slow"), source="external").exists()


def test_node_that_vanishes_is_marked_lost_and_returns(api, gateway):
    register("it-vanish", stack.domain(4))
    process = stack.start_robot("vanish-1", stack.domain(4), "camera_driver")
    node_key = "it-vanish.camera_driver"
    wait_node(api, node_key, alive=True, state="unconfigured")
    assert transition(api, node_key, "configure").status_code == 200
    process.stop()
    wait_node(api, node_key, alive=False, timeout=15)
    response = transition(api, node_key, "activate")
    assert response.status_code == 409 and response.json()["error"]["code"] == "node_offline"
    assert api.get(f"/api/v1/nodes/{node_key}").json()["transitions"] == []
    process = stack.start_robot("vanish-2", stack.domain(4), "camera_driver")
    try:
        # A respawned process starts unconfigured; its history stays with the same node id.
        wait_node(api, node_key, alive=True, state="unconfigured", timeout=15)
        assert ManagedNode.objects.filter(key=node_key).count() == 1
        assert TransitionRecord.objects.filter(node__key=node_key).count() >= 2
    finally:
        process.stop()


def test_robots_added_and_disabled_while_running_are_picked_up(api, gateway):
    process = stack.start_robot("late-robot", stack.domain(5), "planner", namespace="/late")
    try:
        robot = register("it-late", stack.domain(5), namespace="/late")
        wait_node(api, "it-late.late.planner", alive=True, timeout=15)
        robot.enabled = False
        robot.save()
        wait_node(api, "it-late.late.planner", alive=False, timeout=15)
    finally:
        process.stop()
        Robot.objects.filter(name="it-late").update(enabled=False)


def test_namespace_narrows_a_robot_within_a_shared_domain(api, gateway):
    register("it-ns-left", stack.domain(6), namespace="/left")
    register("it-ns-right", stack.domain(6), namespace="/right")
    left = stack.start_robot("ns-left", stack.domain(6), "planner", namespace="/left")
    right = stack.start_robot("ns-right", stack.domain(6), "planner", namespace="/right")
    try:
        wait_node(api, "it-ns-left.left.planner", alive=True)
        wait_node(api, "it-ns-right.right.planner", alive=True)
        assert not ManagedNode.objects.filter(robot__name="it-ns-left", name="/right/planner").exists()
    finally:
        left.stop()
        right.stop()


def test_garbage_on_the_command_queue_does_not_hurt_the_gateway(api, flaky, gateway):
    client = redis.Redis.from_url(settings.REDIS_URL)
    queue = protocol.command_queue(settings.CHANNEL_LAYERS["default"]["CONFIG"]["prefix"], "local")
    for junk in (b"not json", b"[1,2]", json.dumps({"command": "change_state"}).encode()):
        client.lpush(queue, junk)
    wait_node(api, key("/fail"), alive=True)
    assert transition(api, key("/fail"), "explode").status_code == 400
    assert api.get(f"/api/v1/nodes/{key('/fail')}").json()["described_by"] == "node"
    assert gateway.alive()


def test_gateway_stopped_means_503_and_nodes_keep_their_last_state(api, flaky, gateway):
    wait_node(api, key("/fail"), alive=True)
    assert gateway.stop() == 0, gateway.output()
    # A stopped gateway says so in its last beat; the site reads beats at most once a second.
    stack.wait_for(lambda: not gateways.status("local").online, gateways.BEAT_CACHE_S + 1, "the gateway offline")
    response = transition(api, key("/fail"), "configure")
    assert response.status_code == 503 and response.json()["error"]["code"] == "gateway_offline"
    assert api.get(f"/api/v1/nodes/{key('/fail')}").status_code == 200
