"""Discovery and transitions through the real gateway, against real rclpy lifecycle nodes."""
from __future__ import annotations

import subprocess
import sys

import pytest
from django.core.cache import cache

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import LogRecord
from lifecycle_site.gateway_link import gateways
from lifecycle_site.gateway_link.gateways import channel_prefix
from ros_gateway.shared import protocol
from tests import stack
from tests.integration.conftest import register, transition, wait_node

AGV_A, AGV_B = "it-agv-a", "it-agv-b"


@pytest.fixture(scope="module")
def robots(gateway):
    register(AGV_A, stack.domain(1))
    register(AGV_B, stack.domain(2))
    processes = [
        stack.start_robot("agv-a-nodes", stack.domain(1), "joy_to_vel,lidar_driver,camera_driver,joystick",
                          extra=("--generic", "3")),
        stack.start_robot("agv-b-nodes", stack.domain(2), "joy_to_vel"),
    ]
    yield processes
    for process in processes:
        process.stop()


def test_lifecycle_nodes_are_discovered_on_each_robot(api, robots):
    for key in (f"{AGV_A}.joy_to_vel", f"{AGV_A}.lidar_driver", f"{AGV_B}.joy_to_vel"):
        wait_node(api, key, alive=True, state="unconfigured")
    listed = api.get(f"/api/v1/nodes?robot={AGV_A}").json()["nodes"]
    names = {n["name"] for n in listed}
    assert {"/joy_to_vel", "/lidar_driver", "/generic_000"} <= names
    assert "/joystick" not in names, "a plain (non-lifecycle) node is not a managed node"
    node = next(n for n in listed if n["name"] == "/lidar_driver")
    assert node["state"] == {"id": 1, "label": "unconfigured"}
    assert node["transitions"] == [{"id": 1, "label": "configure"}, {"id": 5, "label": "shutdown"}]
    robots_list = {r["name"]: r for r in api.get("/api/v1/robots").json()["robots"]}
    assert robots_list[AGV_A]["online"] and robots_list[AGV_A]["node_count"] >= 5


def test_full_cycle_through_the_api_is_audited(api, robots):
    key = f"{AGV_A}.lidar_driver"
    wait_node(api, key, alive=True, state="unconfigured")
    path = [("configure", "inactive"), ("activate", "active"), ("deactivate", "inactive"),
            ("cleanup", "unconfigured"), ("configure", "inactive"), ("activate", "active")]
    for name, goal in path:
        response = transition(api, key, name)
        assert response.status_code == 200, response.json()
        body = response.json()
        assert body["success"] and body["to"]["label"] == goal and body["duration_ms"] > 0
    detail = api.get(f"/api/v1/nodes/{key}").json()
    assert detail["state"]["label"] == "active" and detail["described_by"] == "node"
    assert {"id": 3, "label": "active"} in detail["available_states"]
    assert any(edge["label"] == "deactivate" for edge in detail["transition_graph"])
    records = api.get(f"/api/v1/transitions?node={key}&limit=6").json()["transitions"]
    assert [r["transition"]["label"] for r in reversed(records)] == [p[0] for p in path]
    assert {(r["source"], r["requested_by"], r["outcome"]) for r in records} == {("api", "ivan-operator", "succeeded")}
    assert not TransitionRecord.objects.filter(node__key=key, source="external").exists()


@pytest.mark.parametrize("index, path", [
    (0, []), (1, ["configure"]), (2, ["configure", "activate"]),
])
def test_shutdown_from_every_primary_state_reaches_finalized(api, robots, index, path):
    key = f"{AGV_A}.generic_{index:03d}"
    wait_node(api, key, alive=True)
    for name in path:
        assert transition(api, key, name).status_code == 200
    response = transition(api, key, "shutdown")
    assert response.status_code == 200 and response.json()["to"]["label"] == "finalized"
    expected_id = {0: 5, 1: 6, 2: 7}[index]  # unconfigured/inactive/active_shutdown
    assert response.json()["transition"]["id"] == expected_id
    finalized = transition(api, key, "configure")
    assert finalized.status_code == 409 and finalized.json()["error"]["valid_transitions"] == []


def test_invalid_transition_is_409_with_the_valid_ones(api, robots):
    key = f"{AGV_B}.joy_to_vel"
    wait_node(api, key, alive=True, state="unconfigured")
    response = transition(api, key, "activate")
    assert response.status_code == 409
    error = response.json()["error"]
    assert error["code"] == "invalid_transition" and error["state"]["label"] == "unconfigured"
    assert [t["label"] for t in error["valid_transitions"]] == ["configure", "shutdown"]
    assert "activate" in error["message"] and "configure" in error["message"]
    record = TransitionRecord.objects.get(id=error["record_id"])
    assert record.outcome == "rejected" and record.source == "api"


def test_same_named_nodes_on_two_robots_stay_apart(api, robots):
    a, b = f"{AGV_A}.joy_to_vel", f"{AGV_B}.joy_to_vel"
    wait_node(api, a, alive=True, state="unconfigured")
    wait_node(api, b, alive=True, state="unconfigured")
    assert transition(api, a, "configure").status_code == 200
    assert api.get(f"/api/v1/nodes/{b}").json()["state"]["label"] == "unconfigured"
    assert transition(api, b, 1).status_code == 200  # numeric id works too
    assert transition(api, a, "cleanup").status_code == 200
    assert api.get(f"/api/v1/nodes/{b}").json()["state"]["label"] == "inactive"


def test_transition_by_another_tool_is_seen_and_recorded_as_external(api, robots):
    key = f"{AGV_B}.joy_to_vel"
    wait_node(api, key, alive=True)
    state = api.get(f"/api/v1/nodes/{key}").json()["state"]["label"]
    if state == "unconfigured":
        assert transition(api, key, "configure").status_code == 200
    before = TransitionRecord.objects.filter(node__key=key, source="external").count()
    result = subprocess.run(
        [sys.executable, "tests/integration/ros_call.py", str(stack.domain(2)), "/joy_to_vel", "3"],
        cwd=stack.ROOT, env=stack.environment(), capture_output=True, text=True, timeout=60,
    )
    assert result.stdout.strip() == "success", result.stdout + result.stderr
    wait_node(api, key, state="active", timeout=10)
    stack.wait_for(
        lambda: TransitionRecord.objects.filter(node__key=key, source="external").count() > before, 10,
        "the external transition in the audit log",
    )
    record = TransitionRecord.objects.filter(node__key=key, source="external").first()
    assert (record.transition_label, record.start_state_label, record.result_state_label, record.outcome) == (
        "activate", "inactive", "active", "succeeded")
    assert record.requested_by is None


def test_node_logs_arrive_from_rosout(api, robots):
    key = f"{AGV_A}.joy_to_vel"
    wait_node(api, key, alive=True)
    stack.wait_for(lambda: LogRecord.objects.filter(node__key=key).exists(), 15, "log records of joy_to_vel")
    records = api.get(f"/api/v1/nodes/{key}/logs?limit=50").json()["records"]
    assert records and all(r["logger"] == "joy_to_vel" for r in records)
    assert {"stamp", "level", "message", "function", "line"} <= set(records[0])
    # Plain nodes' logs are kept for their robot too (shown in the robot's log view).
    stack.wait_for(lambda: LogRecord.objects.filter(robot__name=AGV_A, logger="joystick").exists(), 15,
                   "log records of the plain joystick node")


def test_state_changes_are_pushed_to_the_channels_groups(api, robots):
    """What live pages subscribe to: the node's group and its robot's group get the change."""
    import asyncio

    from asgiref.sync import async_to_sync, sync_to_async
    from channels.layers import get_channel_layer

    from lifecycle_site.fleet.models import Robot
    from ros_gateway.shared import protocol

    key = f"{AGV_A}.camera_driver"
    robot_id = Robot.objects.get(name=AGV_A).id

    async def scenario():
        layer = get_channel_layer()
        node_channel, robot_channel = await layer.new_channel(), await layer.new_channel()
        await layer.group_add(protocol.node_group(key), node_channel)
        await layer.group_add(protocol.robot_group(robot_id), robot_channel)
        response = await sync_to_async(transition)(api, key, "configure")
        assert response.status_code == 200
        seen = []
        while not any(m.get("node", {}).get("state", {}).get("label") == "inactive" for m in seen):
            seen.append(await asyncio.wait_for(layer.receive(node_channel), 10))
        robot_message = await asyncio.wait_for(layer.receive(robot_channel), 10)
        assert robot_message["type"] in ("node.state", "node.logs", "audit.record")

    wait_node(api, key, alive=True, state="unconfigured")
    async_to_sync(scenario)()


def test_node_description_is_asked_of_the_node_once_a_minute_not_on_every_read(api, robots):
    """GET /api/v1/nodes/{id} answers with the node's own states and graph; the site keeps them
    (they are fixed in the node's code) rather than making two gateway round trips per read."""
    key = f"{AGV_B}.joy_to_vel"
    wait_node(api, key, alive=True)
    client = gateways.redis_client()
    pattern = protocol.gateway_key(channel_prefix(), "local", "claim:*")

    def commands_taken() -> int:
        return sum(1 for _ in client.scan_iter(pattern, count=1000))

    cache.clear()  # what an earlier test's read left
    before = commands_taken()
    first = api.get(f"/api/v1/nodes/{key}").json()
    after_first = commands_taken()
    second = api.get(f"/api/v1/nodes/{key}").json()
    assert first["described_by"] == second["described_by"] == "node"
    assert after_first - before == 2, "states and graph, asked of the node the first time"
    assert commands_taken() == after_first, "the second read asked the gateway nothing"
    assert second["transition_graph"] == first["transition_graph"]
