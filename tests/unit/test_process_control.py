"""Asking for a process action without a gateway that answers (lifecycle_site/operations/processes.py
and its API): every refusal is plain, none is a 5xx, and what did not reach the robot is on
record with who asked."""
from __future__ import annotations

import json

import pytest
from django.test import Client

from lifecycle_site.audit.models import ProcessRecord
from lifecycle_site.fleet.models import ManagedNode, ProcessProfile, Robot
from ros_gateway.shared import state_machine as sm


@pytest.fixture
def profile(db) -> ProcessProfile:
    robot = Robot.objects.create(name="proc-offline", domain_id=42)
    return ProcessProfile.objects.create(robot=robot, name="drivers", command="/usr/bin/true")


def post(client: Client, body, process: str = "drivers"):
    data = body if isinstance(body, (str, bytes)) else json.dumps(body)
    return client.post(f"/api/v1/robots/proc-offline/processes/{process}", data, content_type="application/json")


def test_an_offline_gateway_refuses_at_once_and_the_attempt_is_recorded(operator_client, profile, redis_server):
    answer = post(operator_client, {"action": "restart"})
    assert answer.status_code == 503 and answer.json()["error"]["code"] == "gateway_offline"
    record = ProcessRecord.objects.get(pk=answer.json()["error"]["record_id"])
    assert (record.action, record.outcome, record.source, record.requested_by_name, record.profile) == (
        "restart", "rejected", "api", "olga-operator", profile)
    assert record.message.startswith("Gateway local is offline (")


def test_a_disabled_profile_is_refused_and_recorded(operator_client, profile):
    ProcessProfile.objects.filter(pk=profile.pk).update(enabled=False)
    answer = post(operator_client, {"action": "start"})
    assert answer.status_code == 409 and answer.json()["error"]["code"] == "process_disabled"
    assert "The launch profile drivers of proc-offline is disabled; an admin enables it." == \
        answer.json()["error"]["message"]
    assert ProcessRecord.objects.get().outcome == "rejected"


@pytest.mark.parametrize("body, process, status, code", [
    ({"action": "reboot"}, "drivers", 400, "unknown_action"),
    ({"action": ["stop"]}, "drivers", 400, "unknown_action"),
    ({}, "drivers", 400, "missing_field"),
    ("[1, 2]", "drivers", 400, "malformed_json"),
    ("{not json", "drivers", 400, "malformed_json"),
    ({"action": "stop"}, "sshd", 404, "unknown_process"),
])
def test_bad_requests_are_refused_plainly_and_nothing_is_sent(operator_client, profile, body, process, status, code):
    answer = post(operator_client, body, process)
    assert (answer.status_code, answer.json()["error"]["code"]) == (status, code), answer.json()
    assert not ProcessRecord.objects.exists()


def test_viewers_see_the_processes_but_may_not_act(viewer_client, profile):
    listing = viewer_client.get("/api/v1/robots/proc-offline/processes")
    assert listing.status_code == 200 and listing.json()["processes"][0]["status"] == "unknown"
    assert post(viewer_client, {"action": "restart"}).status_code == 403
    assert viewer_client.get("/api/v1/robots/nobody/processes").status_code == 404


def test_the_node_page_offers_to_restart_the_process_that_runs_the_node(operator_client, viewer_client, profile,
                                                                         redis_server):
    node = ManagedNode.objects.create(robot=profile.robot, name="/lidar", alive=False, state_id=sm.FINALIZED,
                                      state_label="finalized", supervised_by="drivers")
    page = operator_client.get(f"/nodes/{node.key}/").content.decode()
    assert "Restart process drivers" in page and "/robots/proc-offline/processes/drivers/restart" in page
    assert "Restart process" not in viewer_client.get(f"/nodes/{node.key}/").content.decode()
    answer = operator_client.post("/robots/proc-offline/processes/drivers/restart", {"from": "node"},
                                  HTTP_HX_REQUEST="true")
    assert answer.status_code == 200 and "Gateway local is offline (" in answer.content.decode()
    assert "processes-live" not in answer.content.decode()  # the node page has none to update
    assert ProcessRecord.objects.get().source == "dashboard"
    ManagedNode.objects.filter(pk=node.pk).update(supervised_by="")
    assert "Restart process" not in operator_client.get(f"/nodes/{node.key}/").content.decode()
