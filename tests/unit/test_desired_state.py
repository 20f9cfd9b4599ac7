"""A node's desired state (lifecycle_site/operations/desired_state.py), set from the API and the node
page through the same operation: a state, or cleared; anything else refused the same way by both."""
from __future__ import annotations

import pytest
from django.test import Client
from django.urls import reverse

from lifecycle_site.fleet.models import ManagedNode, Robot
from ros_gateway.shared import state_machine as sm

REFUSED = "desired_state must be unconfigured, inactive, active or null."


@pytest.fixture
def node(db) -> ManagedNode:
    robot = Robot.objects.create(name="wish-agv", domain_id=95)
    return ManagedNode.objects.create(robot=robot, name="/lidar", alive=True, state_id=sm.ACTIVE, state_label="active")


def test_the_page_and_the_api_set_clear_and_refuse_alike(operator_client: Client, node: ManagedNode):
    page = reverse("dashboard:node-desired-state", args=[node.key])
    assert operator_client.post(page, {"desired_state": "active"}, HTTP_HX_REQUEST="true").status_code == 200
    assert ManagedNode.objects.get(pk=node.pk).desired_state == "active"
    refused = operator_client.post(page, {"desired_state": "none"}, HTTP_HX_REQUEST="true")
    assert refused.status_code == 400 and REFUSED in refused.content.decode()
    assert ManagedNode.objects.get(pk=node.pk).desired_state == "active"  # kept, not cleared
    api = operator_client.put(f"/api/v1/nodes/{node.key}/desired-state", {"desired_state": "none"},
                              content_type="application/json")
    assert (api.status_code, api.json()["error"]["message"]) == (400, REFUSED)
    assert operator_client.post(page, {"desired_state": ""}, HTTP_HX_REQUEST="true").status_code == 200
    assert ManagedNode.objects.get(pk=node.pk).desired_state == ""
