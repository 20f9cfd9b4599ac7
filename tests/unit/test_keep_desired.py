"""The site's side of keeping desired states (docs/modes.md, "Desired states kept"): the policy set
through the API (all or nothing), what the gateway's config says for it ("paused" after a fight,
"resumed" when an operator lifts it), a gateway's word that it stopped (checked like any fact),
and the alert rule and attention strip that say so."""
from __future__ import annotations

import pytest
from django.test import Client
from django.utils import timezone

from lifecycle_site.alerts import conditions
from lifecycle_site.alerts.models import Rule
from lifecycle_site.dashboard import attention
from lifecycle_site.fleet.models import Gateway, ManagedNode, Robot
from lifecycle_site.gateway_link.gateway_config import build_config
from lifecycle_site.ingest.facts import apply_facts
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm
from tests.gateway_part import GatewayPart


@pytest.fixture
def node(db) -> ManagedNode:
    gateway = Gateway.objects.create(name="cell-k")
    robot = Robot.objects.create(name="keep-agv", domain_id=42, gateway=gateway, keep_desired="alert")
    return ManagedNode.objects.create(robot=robot, name="/camera", alive=True, state_id=sm.ACTIVE,
                                      state_label="active", desired_state="inactive", last_seen=timezone.now())


def put(client: Client, node: ManagedNode, body: dict):
    return client.put(f"/api/v1/nodes/{node.key}/desired-state", body, content_type="application/json")


def config_of(node: ManagedNode) -> dict:
    return build_config("cell-k")["robots"][0]["nodes"][node.name]


def test_the_policy_is_the_nodes_or_its_robots_and_a_refusal_changes_nothing(operator_client, node):
    assert config_of(node)["keep"] == "alert"  # its robot's
    answer = put(operator_client, node, {"keep": "enforce"})
    assert (answer.status_code, answer.json()["keep"], answer.json()["keep_own"]) == (200, "enforce", "enforce")
    refused = put(operator_client, node, {"desired_state": "active", "keep": "always"})
    assert refused.status_code == 400
    assert "keep must be off, alert, enforce or null" in refused.json()["error"]["message"]
    node.refresh_from_db()
    assert (node.desired_state, node.keep_desired) == ("inactive", "enforce")  # the good half not kept either
    assert put(operator_client, node, {"keep": None}).json()["keep"] == "alert"
    assert put(operator_client, node, {"resume": True}).json()["error"]["code"] == "not_stopped"


def test_a_fight_pauses_the_node_in_the_config_until_an_operator_resumes_it(operator_client, node, viewer_client):
    put(operator_client, node, {"keep": "enforce"})
    part = GatewayPart("cell-k")
    stopped = part.fact(protocol.ENFORCEMENT_STOPPED, robot=node.robot.name, node=node.name,
                        message="another manager keeps changing /camera (...)", changes=4, window_s=600.0,
                        last_change=timezone.now().isoformat())
    applied = apply_facts("cell-k", [stopped, part.fact(protocol.ENFORCEMENT_STOPPED, robot="other-robot",
                                                        node="/x", message="not mine")])
    assert applied.rejected == 1  # a robot of another gateway's
    assert config_of(node)["keep"] == protocol.KEEP_PAUSED and "resumed" not in config_of(node)
    assert put(viewer_client, node, {"resume": True}).status_code == 403
    answer = put(operator_client, node, {"resume": True}).json()
    assert (answer["keep"], answer["enforcement_stopped"]) == ("enforce", None)
    assert config_of(node)["keep"] == "enforce" and config_of(node)["resumed"]


def test_the_not_kept_rule_sees_drift_under_alert_or_enforce_and_a_fight(node):
    rule = Rule.objects.get(name="Desired state not kept")  # (alerts/installed_rules.py)
    found = conditions.current(rule, timezone.now())
    assert found[node.key].summary == ("Node /camera on robot keep-agv was moved to active; its desired state is "
                                       "inactive, kept against other tools.")
    Robot.objects.filter(pk=node.robot_id).update(keep_desired="off")
    assert conditions.current(rule, timezone.now()) == {}
    ManagedNode.objects.filter(pk=node.pk).update(keep_desired="enforce", enforcement_stopped=timezone.now(),
                                                  enforcement_note="another manager keeps changing /camera")
    summary = conditions.current(rule, timezone.now())[node.key].summary
    assert summary.endswith("another manager keeps changing /camera.")
    items = attention._read(gateway_views=[])["items"]
    assert [(i["label"], i["reason"]) for i in items] == [
        ("another manager keeps changing it", "another manager keeps changing /camera")]
