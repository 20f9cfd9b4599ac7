"""The fleet page's "needs attention" list (dashboard/attention.py): what it lists, worst first,
with the node's own reason; what it leaves out; and its cost, the same few queries at any size."""
from __future__ import annotations

from datetime import timedelta

from django.db import connection
from django.test.utils import CaptureQueriesContext
from django.utils import timezone

from lifecycle_site.alerts.models import Alert
from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.dashboard import attention
from lifecycle_site.fleet.models import ManagedNode, Robot
from ros_gateway.shared import state_machine as sm
from tests.unit.test_fleet_collapse import make_fleet


def node(robot: Robot, name: str, **fields) -> ManagedNode:
    now = timezone.now()
    values = {"alive": True, "state_id": sm.UNCONFIGURED, "state_label": "unconfigured", "first_seen": now,
              "last_seen": now, **fields}
    return ManagedNode.objects.create(robot=robot, name=name, **values)


def record(target: ManagedNode, outcome: str, seconds_ago: float, label: str = "configure", error: str = "") -> None:
    TransitionRecord.objects.create(node=target, robot=target.robot, robot_name=target.robot.name,
                                    node_name=target.name, transition_label=label, outcome=outcome, source="api",
                                    error=error, requested_at=timezone.now() - timedelta(seconds=seconds_ago))


def offline_view(name: str, robots: list[str]) -> dict:
    return {"name": name, "robots": robots, "online": False, "status": "quarantined",
            "reason_plain": "the site cut it off at 10:00:00 UTC: its keys held 70 MB", "reason_since": None}


def test_problems_worst_first_with_the_nodes_own_reason(db):
    robot = Robot.objects.create(name="at-agv", domain_id=40)
    off = Robot.objects.create(name="at-off", domain_id=41, enabled=False)
    failed = node(robot, "/flaky")
    record(failed, "succeeded", 60)
    record(failed, "failed", 5, "activate", "on_activate raised RuntimeError: simulated driver fault")
    fixed = node(robot, "/fixed")
    record(fixed, "failed", 60, error="old trouble")
    record(fixed, "succeeded", 5)  # its last transition went well: nothing to see
    node(robot, "/drifting", state_id=sm.INACTIVE, state_label="inactive", desired_state="active")
    node(robot, "/settled", state_id=sm.ACTIVE, state_label="active", desired_state="active")
    node(robot, "/silent", alive=False, gone_reason="unreachable")
    crashed = node(robot, "/crashed", alive=False, gone_reason="process_lost")
    record(crashed, "process_lost", 3, "", "The node's process ended during activate")
    alerted = node(robot, "/alerted")
    node(robot, "/waiting", alive=False, first_seen=None, last_seen=None)  # never seen: not a problem yet
    node(off, "/lidar", alive=False)  # its robot is disabled: not watched
    now = timezone.now()
    Alert.objects.create(rule_name="hot", subject=alerted.key, robot_name=robot.name, node_name=alerted.name,
                         summary="Node /alerted on robot at-agv is hot.", since=now, fired_at=now)
    Alert.objects.create(rule_name="drift", subject=f"{robot.name}.drifting", robot_name=robot.name,
                         node_name="/drifting", summary="not desired", since=now, fired_at=now)

    found = attention.current([offline_view("cell-q", ["at-q"])])
    kinds = [(item["kind"], item["node"] or item["gateway"]) for item in found["items"]]
    # A gateway cut off takes all its robots with it: it leads.
    assert kinds == [("gateway", "cell-q"), ("failed", "/flaky"), ("not_desired", "/drifting"), ("lost", "/silent"),
                     ("process_lost", "/crashed"), ("alert", "/alerted")], kinds
    assert "quarantined" in found["items"][0]["label"] and "70 MB" in found["items"][0]["reason"]
    first = found["items"][1]
    assert first["label"] == "activate failed"
    assert first["reason"] == "on_activate raised RuntimeError: simulated driver fault"
    drifting = found["items"][2]
    assert drifting["label"] == "not in its desired state: inactive, desired state active"
    assert drifting["also"] == ["alert firing: drift"]
    assert found["items"][3]["label"] == "not answering"
    assert found["items"][4]["reason"] == "The node's process ended during activate"
    assert found["items"][5]["reason"] == "Node /alerted on robot at-agv is hot."
    assert found["count"] == 6 and found["gateways"] == ["cell-q"]
    assert sorted(found["keys"]) == sorted(f"at-agv.{n}" for n in ("flaky", "drifting", "silent", "crashed",
                                                                    "alerted"))


def test_a_node_back_up_but_not_in_its_desired_state_is_not_said_to_be_lost(db):
    """Its last record tells of an ended episode (its process ended, it came back): that is not
    why it is not in its desired state now, and the strip must not say so beside a running row."""
    robot = Robot.objects.create(name="at-back", domain_id=42)
    back = node(robot, "/lidar", desired_state="active")
    record(back, "process_lost", 30, "", "The process of /lidar on at-back ended: its node left the ROS graph")
    item, = attention.current([])["items"]
    assert item["label"] == "not in its desired state: unconfigured, desired state active"
    assert item["reason"] == ""


def test_the_same_few_queries_at_200_and_1000_nodes(db):
    def queries() -> int:
        from django.core.cache import cache

        cache.clear()
        with CaptureQueriesContext(connection) as captured:
            found = attention.current([])
        assert found["count"] > 0
        return len(captured.captured_queries)

    robots = make_fleet(robots=2, per_robot=100, prefix="few")
    for target in ManagedNode.objects.filter(robot__in=robots)[:50]:
        record(target, "failed", 10, error="boom")
    small = queries()
    robots = make_fleet(robots=8, per_robot=100, prefix="many")
    for target in ManagedNode.objects.filter(robot__in=robots)[:400]:
        record(target, "failed", 10, error="boom")
    assert queries() <= small <= 4  # the nodes with their last record, the alerts, the records listed, diagnostics
