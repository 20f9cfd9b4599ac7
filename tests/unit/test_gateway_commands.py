"""Commands go to the robot's own gateway, through its own queue on the real Redis (the test
answers as that gateway would); a gateway that is offline refuses at once, on the record,
and the robots of other gateways do not notice."""
from __future__ import annotations

import json
import re
import threading
import time

import pytest
from django.test import Client

from lifecycle_site.audit.models import ParameterRecord, TransitionRecord
from lifecycle_site.fleet.models import Gateway, GroupRun, ManagedNode, Robot
from lifecycle_site.gateway_link import gateways
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm
from tests.conftest import client_of
from tests.gateway_part import GatewayPart, clear_streams


@pytest.fixture
def cells(transactional_db, redis_server):
    parts = {}
    for name in ("cell-a", "cell-b"):
        clear_streams(name)
        gateway = Gateway.objects.create(name=name)
        robot = Robot.objects.create(name=f"agv-{name[-1]}", domain_id=43, gateway=gateway)
        ManagedNode.objects.create(robot=robot, name="/lidar", alive=True, state_id=sm.UNCONFIGURED,
                                   state_label="unconfigured", order=2)
        ManagedNode.objects.create(robot=robot, name="/camera", alive=True, state_id=sm.UNCONFIGURED,
                                   state_label="unconfigured", order=1)
        parts[name] = GatewayPart(name)
    parts["cell-a"].beat(at=time.time() - 125)  # silent for two minutes
    parts["cell-b"].beat()
    client = client_of("rita-router", "operator")
    return parts, client


def in_thread(call):
    """Run a request in a thread of its own (the test answers as the gateway meanwhile)."""
    box: dict = {}
    thread = threading.Thread(target=lambda: box.update(response=call()), daemon=True)
    thread.start()
    return thread, box


def transition(client: Client, key: str, name: str = "configure"):
    return client.post(f"/api/v1/nodes/{key}/transition", json.dumps({"transition": name}),
                       content_type="application/json")


def test_an_offline_gateway_refuses_at_once_and_another_gateways_robot_gets_its_command(cells):
    parts, client = cells
    started = time.monotonic()
    refused = transition(client, "agv-a.lidar")
    assert time.monotonic() - started < 1.0
    assert refused.status_code == 503 and refused.json()["error"]["code"] == "gateway_offline"
    message = refused.json()["error"]["message"]
    assert re.fullmatch(r"Gateway cell-a is offline \(no heartbeat since \d\d:\d\d:\d\d UTC, 2 min ago\); "
                        r"nothing was sent to agv-a\.", message), message
    record = TransitionRecord.objects.get(robot_name="agv-a")
    assert (record.outcome, record.error, record.requested_by_name) == ("rejected", message, "rita-router")
    assert refused.json()["error"]["record_id"] == record.id
    assert parts["cell-a"].queue_length() == 0

    thread, box = in_thread(lambda: transition(client, "agv-b.lidar"))
    command = parts["cell-b"].take_command()
    assert command is not None and parts["cell-a"].queue_length() == 0
    assert (command["command"], command["robot"], command["node"], command["transition"]) == (
        protocol.CHANGE_STATE, "agv-b", "/lidar", "configure")
    b = parts["cell-b"]
    facts = [b.fact(protocol.NODE_STATE, robot="agv-b", node="/lidar", state_id=sm.INACTIVE),
             b.transition("agv-b", "/lidar", sm.CONFIGURE, "configure", sm.UNCONFIGURED, sm.INACTIVE,
                          user_id=command["user_id"])]
    b.reply(command, ok=True, outcome="succeeded", transition={"id": 1, "label": "configure"},
            **{"from": sm.state_dict(sm.UNCONFIGURED)}, to=sm.state_dict(sm.INACTIVE), duration_ms=12.5, message="",
            valid_transitions=[], facts=facts)
    thread.join(10)
    answer = box["response"]
    assert answer.status_code == 200, answer.content
    record = TransitionRecord.objects.get(robot_name="agv-b")  # written before the answer, once
    assert answer.json()["record_id"] == record.id and record.fact_id == facts[1]["id"]
    assert record.requested_by_name == "rita-router"
    assert ManagedNode.objects.get(key="agv-b.lidar").state_label == "inactive"


def test_parameters_refused_by_an_offline_gateway_are_audited_one_by_one(cells):
    _, client = cells
    response = client.patch("/api/v1/nodes/agv-a.lidar/parameters", json.dumps({"rate": 5, "frame": "laser"}),
                            content_type="application/json")
    assert response.status_code == 503 and "Gateway cell-a is offline" in response.json()["error"]["message"]
    records = {r.name: r for r in ParameterRecord.objects.all()}
    assert set(records) == {"rate", "frame"}
    assert {(r.outcome, r.new_value, r.source) for r in records.values()} == {("rejected", 5, "api"),
                                                                             ("rejected", "laser", "api")}
    assert all("Gateway cell-a is offline" in r.reason for r in records.values())


def test_parameters_set_through_the_gateway_are_on_record_before_the_answer(cells):
    parts, client = cells
    thread, box = in_thread(lambda: client.patch("/api/v1/nodes/agv-b.lidar/parameters", json.dumps({"rate": 5}),
                                                 content_type="application/json"))
    command = parts["cell-b"].take_command()
    assert (command["command"], command["values"]) == (protocol.SET_PARAMETERS, {"rate": 5})
    b = parts["cell-b"]
    fact = b.fact(protocol.PARAMETER, robot="agv-b", node="/lidar", name="rate", old=10, new=5, outcome="succeeded",
                  reason="", source="api", user_id=command["user_id"], **protocol.vouching(command, "rate"))
    b.reply(command, ok=True, results=[{"name": "rate", "old": 10, "new": 5, "successful": True, "reason": ""}],
            facts=[fact])
    thread.join(10)
    assert box["response"].status_code == 200
    record = ParameterRecord.objects.get()
    assert (record.fact_id, record.requested_by_name, record.old_value) == (fact["id"], "rita-router", 10)


def test_runs_carry_their_tiers_and_fail_at_once_when_the_gateway_is_offline(cells):
    parts, client = cells
    response = client.post("/api/v1/robots/agv-a/operations", json.dumps({"operation": "bringup"}),
                           content_type="application/json")
    assert response.status_code == 503
    run = GroupRun.objects.get(robot__name="agv-a")
    assert run.status == "failed" and run.message.startswith("Gateway cell-a is offline")

    thread, box = in_thread(lambda: client.post("/api/v1/robots/agv-b/operations",
                                                json.dumps({"operation": "pause", "policy": "continue"}),
                                                content_type="application/json"))
    command = parts["cell-b"].take_command()
    spec = command["run"]
    run = GroupRun.objects.get(robot__name="agv-b")
    assert command["command"] == protocol.START_RUN
    assert spec == {"id": run.id, "robot": "agv-b", "operation": "pause", "policy": "continue", "node_timeout": 5.0,
                    "tiers": [["/camera"], ["/lidar"]], "source": "api", "user_id": run.requested_by_id}
    parts["cell-b"].reply(command, ok=True, run_id=run.id)
    thread.join(10)
    assert box["response"].status_code == 202


def test_the_config_follows_the_robots_of_each_gateway(cells):
    parts, _ = cells
    redis = parts["cell-a"].redis

    def config(name: str) -> dict:
        return json.loads(redis.get(protocol.config_key(gateways.channel_prefix(), name)))

    robot = Robot.objects.get(name="agv-b")
    robot.gateway = Gateway.objects.get(name="cell-a")
    robot.save()
    assert [r["name"] for r in config("cell-a")["robots"]] == ["agv-a", "agv-b"]
    assert config("cell-b")["robots"] == []
    before = config("cell-a")["version"]
    node = ManagedNode.objects.get(key="agv-b.lidar")
    node.desired_state = "active"
    node.save(update_fields=["desired_state"])
    after = config("cell-a")
    assert after["version"] != before
    assert after["robots"][1]["nodes"]["/lidar"] == {"order": 2, "desired_state": "active", "keep": "off"}


@pytest.mark.parametrize("timeout", ["1" + "0" * 400, "0", "-3", "true", '"5"', "26"])
def test_a_run_timeout_that_is_no_usable_number_of_seconds_is_refused_before_anything_starts(cells, timeout):
    _parts, client = cells
    response = client.post("/api/v1/robots/agv-a/operations", '{"operation": "bringup", "timeout": %s}' % timeout,
                           content_type="application/json")
    assert response.status_code == 400, response.content
    assert response.json()["error"]["code"] == "invalid_field" and "at most 25" in response.json()["error"]["message"]
    assert not GroupRun.objects.filter(robot__name="agv-a").exists()
