"""Requesting a transition on behalf of a user (lifecycle_site/operations/transitions.py), without a
robot: what cannot be sent is answered with a reason and recorded, whatever the adapter."""
from __future__ import annotations

import pytest

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import ManagedNode, Robot
from lifecycle_site.operations.transitions import request_transition
from ros_gateway.shared import state_machine as sm
from tests.conftest import make_user


@pytest.fixture
def node(db) -> ManagedNode:
    robot = Robot.objects.create(name="unit-agv", domain_id=99)
    return ManagedNode.objects.create(robot=robot, name="/joy_to_vel", alive=True, state_id=sm.INACTIVE,
                                      state_label="inactive")


@pytest.mark.parametrize("case, says", [
    ("robot disabled", "Robot unit-agv is disabled: its nodes are not watched. Enable it in the admin."),
    ("node gone", "/joy_to_vel is not running on unit-agv; it was last seen never."),
])
def test_what_cannot_reach_a_node_is_refused_and_recorded_with_who_and_why(node, case, says):
    if case == "robot disabled":
        Robot.objects.filter(pk=node.robot_id).update(enabled=False)
        node.robot.refresh_from_db()
    else:
        node.alive = False
    user = make_user("olga-operator", "operator")
    outcome = request_transition(node, "activate", user, "cli")
    assert (outcome.succeeded, outcome.status, outcome.code, outcome.message) == (False, 409, "node_offline", says)
    record = TransitionRecord.objects.get(pk=outcome.data["record_id"])
    assert (record.outcome, record.source, record.requested_by_name, record.error) == ("rejected", "cli",
                                                                                      "olga-operator", says)
    assert (record.transition_label, record.start_state_label) == ("activate", "inactive")


def test_an_offline_gateway_refuses_at_once_and_the_attempt_is_recorded(node, redis_server):
    outcome = request_transition(node, 3, make_user("olga-operator", "operator"), "dashboard")
    assert (outcome.status, outcome.code) == (503, "gateway_offline")
    # "(it has never reported)", or since its last beat when an earlier test wrote one.
    assert outcome.message.startswith("Gateway local is offline (")
    assert outcome.message.endswith("; nothing was sent to unit-agv.")
    record = TransitionRecord.objects.get(pk=outcome.data["record_id"])
    assert (record.transition_label, record.source, record.outcome) == ("activate", "dashboard", "rejected")
