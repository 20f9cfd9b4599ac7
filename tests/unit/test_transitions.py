"""Requesting a transition on behalf of a user (lifecycle_site/operations/transitions.py), without a
robot: what cannot be sent is answered with a reason and recorded, whatever the adapter."""
from __future__ import annotations

import pytest

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import ManagedNode, Robot
from lifecycle_site.operations.transitions import TransitionRefused, named, request_transition
from ros_gateway.shared import state_machine as sm
from tests.conftest import make_user


@pytest.fixture
def node(db) -> ManagedNode:
    robot = Robot.objects.create(name="unit-agv", domain_id=99)
    return ManagedNode.objects.create(robot=robot, name="/joy_to_vel", alive=True, state_id=sm.INACTIVE,
                                      state_label="inactive")


@pytest.mark.parametrize("case, says", [
    ("robot disabled", "Robot unit-agv is disabled: its nodes are not watched. Enable it in the admin."),
    ("node gone", "/joy_to_vel is not running on unit-agv, and has never been seen running."),
])
def test_what_cannot_reach_a_node_is_refused_and_recorded_with_who_and_why(node, case, says):
    if case == "robot disabled":
        Robot.objects.filter(pk=node.robot_id).update(enabled=False)
        node.robot.refresh_from_db()
    else:
        node.alive = False
    user = make_user("olga-operator", "operator")
    with pytest.raises(TransitionRefused) as refused:
        request_transition(node, "activate", user, "cli")
    assert (refused.value.status, refused.value.code, refused.value.message) == (409, "node_offline", says)
    record = TransitionRecord.objects.get(pk=refused.value.details["record_id"])
    assert (record.outcome, record.source, record.requested_by_name, record.error) == ("rejected", "cli",
                                                                                      "olga-operator", says)
    assert (record.transition_label, record.start_state_label) == ("activate", "inactive")


def test_an_offline_gateway_refuses_at_once_and_the_attempt_is_recorded(node, redis_server):
    with pytest.raises(TransitionRefused) as refused:
        request_transition(node, 3, make_user("olga-operator", "operator"), "dashboard")
    assert (refused.value.status, refused.value.code) == (503, "gateway_offline")
    # "(it has never reported)", or since its last beat when an earlier test wrote one.
    assert refused.value.message.startswith("Gateway local is offline (")
    assert refused.value.message.endswith("; nothing was sent to unit-agv.")
    record = TransitionRecord.objects.get(pk=refused.value.details["record_id"])
    assert (record.transition_label, record.source, record.outcome) == ("activate", "dashboard", "rejected")


@pytest.mark.parametrize("asked, meant", [("activate", "activate"), (" Activate ", "activate"), ("3", 3), (3, 3),
                                          ("shutdown", "shutdown")])
def test_a_transition_is_named_by_label_or_id_the_same_way_for_every_adapter(asked, meant):
    assert named(asked) == meant


@pytest.mark.parametrize("asked, code, says", [
    ("jump", "unknown_transition", "'jump' is not a lifecycle transition; use one of configure, "),
    ("9" * 5000, "unknown_transition", "… (5,002 characters) is not a lifecycle transition"),
    (99, "unknown_transition", "99 is not a lifecycle transition"),
    (True, "invalid_field", "'transition' must be a label such as \"activate\" or a numeric id."),
    (["configure"], "invalid_field", "must be a label"),
])
def test_what_names_no_transition_is_refused_before_anything_is_recorded(node, asked, code, says):
    with pytest.raises(TransitionRefused) as refused:
        request_transition(node, asked, make_user("olga-operator", "operator"), "api")
    assert (refused.value.code, refused.value.status) == (code, 400)
    assert says in refused.value.message
    assert not TransitionRecord.objects.exists()
