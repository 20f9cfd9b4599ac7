"""Alert rules against the real test database (and the real Redis for gateway heartbeats and the
ingest loop): which nodes and gateways a rule matches, and an alert's life from firing through
acknowledged to resolved."""
from __future__ import annotations

import time
from datetime import timedelta

import pytest
from django.utils import timezone

from lifecycle_site.alerts import lifecycle
from lifecycle_site.alerts.engine import Evaluator
from lifecycle_site.alerts.models import Alert, Rule
from lifecycle_site.fleet.models import Gateway, ManagedNode, Robot
from lifecycle_site.ingest.management.commands.ingest import Ingest
from lifecycle_site.refusal import Refusal
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm
from tests import stack
from tests.conftest import make_user
from tests.gateway_part import GatewayPart, clear_streams, forget_ingest_processes, iso


@pytest.fixture
def fleet(db):
    cell = Gateway.objects.create(name="al-cell")
    agv = Robot.objects.create(name="al-agv", domain_id=61, gateway=cell)
    arm = Robot.objects.create(name="al-arm", domain_id=62, gateway=Gateway.objects.create(name="al-other"))
    now = timezone.now()
    for robot in (agv, arm):
        for name in ("/lidar_driver", "/planner"):
            ManagedNode.objects.create(robot=robot, name=name, alive=True, state_id=sm.UNCONFIGURED,
                                       state_label="unconfigured", first_seen=now, last_seen=now, state_changed=now)
    return agv, arm


def node(robot: Robot, name: str) -> ManagedNode:
    return ManagedNode.objects.get(robot=robot, name=name)


def set_node(robot: Robot, name: str, **fields) -> None:
    ManagedNode.objects.filter(robot=robot, name=name).update(**fields)


def active(rule: Rule) -> dict[str, Alert]:
    return {a.subject: a for a in Alert.objects.filter(rule=rule, status__in=Alert.ACTIVE)}


def state_fact(robot: str, name: str, state_id: int, at=None, gateway: str = "al-cell") -> dict:
    return {"type": protocol.NODE_STATE, "gateway": gateway, "robot": robot, "node": name, "state_id": state_id,
            "at": iso(at)}


def test_a_state_entered_for_milliseconds_fires_from_the_facts_and_resolves_when_over(fleet):
    agv, _arm = fleet
    rule = Rule.objects.create(name="errors", kind=Rule.Kind.STATE, state="errorprocessing")
    evaluator = Evaluator()
    now = timezone.now()
    # The node passed through errorprocessing; the database already says unconfigured.
    evaluator.observe("al-cell", [state_fact(agv.name, "/planner", sm.ERRORPROCESSING, now),
                                  state_fact(agv.name, "/planner", sm.UNCONFIGURED, now)])
    evaluator.evaluate(now)
    alert = active(rule)["al-agv.planner"]
    assert (alert.status, alert.robot_name, alert.node_name, alert.gateway_name) == (
        "firing", "al-agv", "/planner", "al-cell")
    assert alert.summary == "Node /planner on robot al-agv entered errorprocessing."
    evaluator.evaluate(now + timedelta(seconds=1))
    alert.refresh_from_db()
    assert alert.status == "resolved" and alert.resolved_at is not None


def test_keep_firing_holds_a_brief_state_on_the_pages_for_that_long(fleet):
    agv, _arm = fleet
    rule = Rule.objects.create(name="errors", kind=Rule.Kind.STATE, state="errorprocessing", keep_firing_seconds=60)
    evaluator = Evaluator()
    t0 = timezone.now()
    evaluator.observe("al-cell", [state_fact(agv.name, "/planner", sm.ERRORPROCESSING, t0)])
    evaluator.evaluate(t0)
    evaluator.evaluate(t0 + timedelta(seconds=59))
    assert active(rule)["al-agv.planner"].status == "firing"
    evaluator.evaluate(t0 + timedelta(seconds=61))
    assert not active(rule)


def test_a_state_for_n_seconds_fires_only_once_it_lasted(fleet):
    agv, _arm = fleet
    rule = Rule.objects.create(name="finalized", kind=Rule.Kind.STATE, state="finalized", for_seconds=10)
    evaluator = Evaluator()
    now = timezone.now()
    set_node(agv, "/lidar_driver", state_id=sm.FINALIZED, state_label="finalized", state_changed=now)
    evaluator.observe("al-cell", [state_fact(agv.name, "/lidar_driver", sm.FINALIZED, now)])  # not at once
    evaluator.evaluate(now + timedelta(seconds=9))
    assert not active(rule)
    evaluator.evaluate(now + timedelta(seconds=10))
    alert = active(rule)["al-agv.lidar_driver"]
    assert alert.since == now and alert.summary == "Node /lidar_driver on robot al-agv is finalized."
    evaluator.evaluate(now + timedelta(seconds=20))
    assert Alert.objects.filter(rule=rule).count() == 1  # still the one alert
    set_node(agv, "/lidar_driver", state_id=sm.UNCONFIGURED, state_label="unconfigured")
    evaluator.evaluate(now + timedelta(seconds=21))
    assert not active(rule)


def test_scope_robot_gateway_and_node_pattern(fleet):
    agv, arm = fleet
    for robot in (agv, arm):
        for name in ("/lidar_driver", "/planner"):
            set_node(robot, name, state_id=sm.FINALIZED, state_label="finalized")
    fleet_wide = Rule.objects.create(name="all", kind=Rule.Kind.STATE, state="finalized")
    by_robot = Rule.objects.create(name="arm", kind=Rule.Kind.STATE, state="finalized", robot=arm)
    by_gateway = Rule.objects.create(name="cell", kind=Rule.Kind.STATE, state="finalized",
                                     gateway=Gateway.objects.get(name="al-cell"))
    by_pattern = Rule.objects.create(name="drivers", kind=Rule.Kind.STATE, state="finalized", node_pattern="/*_driver")
    Evaluator().evaluate()
    assert set(active(fleet_wide)) == {"al-agv.lidar_driver", "al-agv.planner", "al-arm.lidar_driver", "al-arm.planner"}
    assert set(active(by_robot)) == {"al-arm.lidar_driver", "al-arm.planner"}
    assert set(active(by_gateway)) == {"al-agv.lidar_driver", "al-agv.planner"}
    assert set(active(by_pattern)) == {"al-agv.lidar_driver", "al-arm.lidar_driver"}


def test_a_vanished_node_fires_and_resolves_when_it_is_back_and_a_never_seen_one_does_not(fleet):
    agv, _arm = fleet
    ManagedNode.objects.create(robot=agv, name="/pinned")  # named before it ever showed up
    rule = Rule.objects.create(name="gone", kind=Rule.Kind.GONE)
    evaluator = Evaluator()
    set_node(agv, "/lidar_driver", alive=False, gone_reason="unreachable", last_seen=timezone.now())
    evaluator.evaluate()
    alerts = active(rule)
    assert set(alerts) == {"al-agv.lidar_driver"}
    assert "stopped answering the gateway's probes" in alerts["al-agv.lidar_driver"].summary
    set_node(agv, "/lidar_driver", alive=True, gone_reason="")
    evaluator.evaluate()
    assert not active(rule)


def test_not_in_desired_state_for_n_seconds(fleet):
    agv, _arm = fleet
    rule = Rule.objects.create(name="drift", kind=Rule.Kind.NOT_DESIRED, for_seconds=5)
    evaluator = Evaluator()
    long_ago = timezone.now() - timedelta(seconds=30)
    set_node(agv, "/planner", desired_state="active", state_label="inactive", state_changed=long_ago)
    set_node(agv, "/lidar_driver", desired_state="unconfigured")  # where it should be
    evaluator.evaluate()
    alert = active(rule)["al-agv.planner"]
    assert alert.summary == "Node /planner on robot al-agv is inactive; its desired state is active."
    set_node(agv, "/planner", state_label="active")
    evaluator.evaluate()
    assert not active(rule)


def test_acknowledged_alerts_keep_who_and_when_then_resolve(fleet):
    agv, _arm = fleet
    rule = Rule.objects.create(name="finalized", kind=Rule.Kind.STATE, state="finalized")
    set_node(agv, "/planner", state_label="finalized")
    evaluator = Evaluator()
    evaluator.evaluate()
    alert = active(rule)["al-agv.planner"]
    olga = make_user("olga-operator", "operator")
    acknowledged = lifecycle.acknowledge(alert.id, olga)
    assert (acknowledged.status, acknowledged.acknowledged_by_name) == ("acknowledged", "olga-operator")
    with pytest.raises(Refusal, match="acknowledged already by olga-operator"):
        lifecycle.acknowledge(alert.id, olga)
    assert lifecycle.counts() == {"firing": 0, "acknowledged": 1}
    evaluator.evaluate()  # still finalized: stays acknowledged, no second alert
    assert Alert.objects.get(pk=alert.pk).status == "acknowledged"
    set_node(agv, "/planner", state_label="unconfigured")
    evaluator.evaluate()
    alert.refresh_from_db()
    assert alert.status == "resolved" and alert.acknowledged_by_name == "olga-operator"
    with pytest.raises(Refusal, match="resolved already"):
        lifecycle.acknowledge(alert.id, olga)


def test_disabling_a_rule_resolves_its_alerts_and_deleting_it_keeps_their_history(fleet):
    agv, _arm = fleet
    rule = Rule.objects.create(name="finalized", kind=Rule.Kind.STATE, state="finalized")
    set_node(agv, "/planner", state_label="finalized")
    evaluator = Evaluator()
    evaluator.evaluate()
    Rule.objects.filter(pk=rule.pk).update(enabled=False)
    evaluator.evaluate()
    assert not active(rule)
    rule.delete()
    assert Alert.objects.get(rule_name="finalized").rule is None


def test_a_gateway_offline_for_n_seconds(fleet, redis_server):
    rule = Rule.objects.create(name="offline", kind=Rule.Kind.GATEWAY_OFFLINE, for_seconds=5)
    evaluator = Evaluator()
    stack.write_beat("al-cell", at=time.time() - 4)  # silent 4 s: offline (after 3 s here), not for 5 s yet
    stack.write_beat("al-other")  # online; a third gateway never reported: not alerted
    Gateway.objects.create(name="al-never")
    evaluator.evaluate()
    assert not active(rule)
    stack.write_beat("al-cell", at=time.time() - 6)
    evaluator.evaluate()
    alert = active(rule)["al-cell"]
    assert alert.gateway_name == "al-cell"
    assert alert.summary.startswith("Gateway al-cell is offline (no heartbeat since")
    stack.write_beat("al-cell")
    evaluator.evaluate()
    assert not active(rule)


def test_a_launch_profile_given_up_is_alerted_until_it_runs_again(fleet):
    from lifecycle_site.fleet.models import ProcessProfile
    agv, arm = fleet
    rule = Rule.objects.create(name="given up", kind=Rule.Kind.PROCESS_GIVEN_UP, robot=agv)
    drivers = ProcessProfile.objects.create(robot=agv, name="drivers", command="/bin/false")
    ProcessProfile.objects.create(robot=arm, name="drivers", command="/bin/false", status="given_up")  # not its robot
    evaluator = Evaluator()
    evaluator.evaluate()
    assert not active(rule)
    ProcessProfile.objects.filter(pk=drivers.pk).update(status="given_up", status_since=timezone.now())
    evaluator.evaluate()
    alert = active(rule)["al-agv:drivers"]
    assert (alert.robot_name, alert.gateway_name) == ("al-agv", "al-cell")
    assert alert.summary.startswith("Process drivers of robot al-agv kept ending and is no longer started again")
    ProcessProfile.objects.filter(pk=drivers.pk).update(status="running")
    evaluator.evaluate()
    assert not active(rule)


def test_rule_validation():
    from django.core.exceptions import ValidationError

    with pytest.raises(ValidationError, match="Choose the state"):
        Rule(name="x", kind=Rule.Kind.STATE).clean()
    with pytest.raises(ValidationError, match="no node pattern"):
        Rule(name="x", kind=Rule.Kind.GATEWAY_OFFLINE, node_pattern="/a*").clean()
    with pytest.raises(ValidationError, match="A process rule has no node pattern"):
        Rule(name="x", kind=Rule.Kind.PROCESS_GIVEN_UP, node_pattern="/a*").clean()


@pytest.fixture
def ingest_cell(transactional_db, redis_server, live_ingest_set_aside):
    forget_ingest_processes()
    clear_streams("al-ingest")
    robot = Robot.objects.create(name="al-ingest-agv", domain_id=63, gateway=Gateway.objects.create(name="al-ingest"))
    return GatewayPart("al-ingest"), robot


def test_the_ingest_loop_fires_on_a_state_it_stored_in_passing(ingest_cell):
    part, robot = ingest_cell
    rule = Rule.objects.create(name="errors", kind=Rule.Kind.STATE, state="errorprocessing")
    part.emit(part.fact(protocol.NODE_SEEN, robot=robot.name, node="/flaky"),
              part.fact(protocol.NODE_STATE, robot=robot.name, node="/flaky", state_id=sm.ERRORPROCESSING),
              part.fact(protocol.NODE_STATE, robot=robot.name, node="/flaky", state_id=sm.UNCONFIGURED))
    ingest = Ingest()
    assert [type(w).__name__ for w in ingest.watchers] == ["Evaluator"]  # registered by the alerts app
    assert ingest.hold_lease()
    try:
        stack.wait_for(lambda: ingest.step(block_ms=100) is not None and Alert.objects.filter(rule=rule).exists(),
                       10, "the alert")
        assert ManagedNode.objects.get(robot=robot, name="/flaky").state_label == "unconfigured"
        stack.wait_for(lambda: ingest.step(block_ms=100) is not None
                       and Alert.objects.get(rule=rule).status == "resolved", 10, "the alert to resolve")
    finally:
        ingest.release_lease()
        for watcher in ingest.watchers:
            watcher.stop()
