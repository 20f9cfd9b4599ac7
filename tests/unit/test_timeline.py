"""The state timeline rebuilt from hand-made audit records with known answers: time in each
state, availability, failures and restarts, the window's edges, a node found inside the
window, stretches the records cannot tell, a gone node, absences before and inside the window,
the read cap, and that every query runs on an index."""
from __future__ import annotations

from datetime import datetime, timedelta, timezone

import pytest
from django.db import connection
from django.test.utils import CaptureQueriesContext

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import ManagedNode, NodeAbsence, Robot
from lifecycle_site.timelines import node as tl
from lifecycle_site.timelines.robot import robot_timeline as robot_timeline_of
from ros_gateway.shared import state_machine as sm

NOW = datetime(2026, 11, 23, 12, 0, tzinfo=timezone.utc)
U, IN, A = sm.UNCONFIGURED, sm.INACTIVE, sm.ACTIVE


def ago(minutes: float) -> datetime:
    return NOW - timedelta(minutes=minutes)


@pytest.fixture
def robot(db) -> Robot:
    return Robot.objects.create(name="tl-agv", domain_id=61)


def make_node(robot: Robot, name: str = "/lidar", state: int = IN, changed: float | None = None,
              first_seen: float = 60 * 24 * 30, desired: str = "active", alive: bool = True,
              last_seen: float | None = 0.5, gone_reason: str = "") -> ManagedNode:
    return ManagedNode.objects.create(
        robot=robot, name=name, state_id=state, state_label=sm.state_label(state), alive=alive,
        state_changed=ago(changed) if changed is not None else None, desired_state=desired,
        first_seen=ago(first_seen) if first_seen is not None else None,
        last_seen=ago(last_seen) if last_seen is not None else None, gone_reason=gone_reason,
    )


def record(node: ManagedNode, minutes_ago: float, start: int | None, result: int | None,
           outcome: str = "succeeded", took_s: float = 0.0) -> TransitionRecord:
    requested = ago(minutes_ago)
    return TransitionRecord.objects.create(
        node=node, robot=node.robot, robot_name=node.robot.name, node_name=node.name,
        start_state_id=start, start_state_label=sm.state_label(start) if start is not None else "",
        result_state_id=result, result_state_label=sm.state_label(result) if result is not None else "",
        outcome=outcome, source="api", requested_at=requested,
        completed_at=requested + timedelta(seconds=took_s) if outcome != "rejected" else None,
        duration_ms=took_s * 1000 if outcome != "rejected" else None,
    )


def minutes(timeline: tl.Timeline) -> dict[str, float]:
    return {state: round(seconds / 60, 3) for state, seconds in timeline.time_in_state.items()}


def test_time_in_state_and_availability_from_the_records(robot):
    node = make_node(robot, state=IN, changed=20)
    record(node, 120, U, IN)  # before the window: the state it starts in
    record(node, 50, IN, A)
    record(node, 20, A, IN)
    timeline = tl.node_timeline(node, "hour", now=NOW)
    assert minutes(timeline) == {"inactive": 30.0, "active": 30.0}
    assert timeline.availability == pytest.approx(0.5)
    assert timeline.outcomes == {"succeeded": 2}  # the record before the window is not counted
    assert (timeline.failures, timeline.restarts, timeline.unknown_seconds) == (0, 0, 0.0)
    assert [s.state for s in timeline.segments] == ["inactive", "active", "inactive"]
    assert timeline.segments[0].start == ago(60) and timeline.segments[-1].end == NOW


def test_a_transition_under_way_at_the_windows_start_ends_inside_it(robot):
    node = make_node(robot, state=A, changed=59)
    record(node, 200, U, IN)
    record(node, 61, IN, A, took_s=120)  # requested before the window, done 1 min into it
    timeline = tl.node_timeline(node, "hour", now=NOW)
    assert minutes(timeline) == {"inactive": 1.0, "active": 59.0}
    assert timeline.outcomes == {} and timeline.rows_read == 0  # requested before the window


def test_failures_and_restarts_are_counted_and_unknown_outcomes_tolerated(robot):
    node = make_node(robot, state=U, changed=5)
    record(node, 300, U, A)
    record(node, 55, A, A, "failed")
    record(node, 50, A, None, "timed_out")
    record(node, 45, A, None, "rejected")
    record(node, 40, A, None, "process_lost")
    record(node, 30, None, U, "process_restarted")
    record(node, 25, U, U, "something_new")  # an outcome the audit log may learn later
    timeline = tl.node_timeline(node, "hour", now=NOW)
    assert timeline.failures == 3 and timeline.restarts == 1
    assert timeline.outcomes["something_new"] == 1 and timeline.outcomes["rejected"] == 1
    spent = minutes(timeline)
    # timed out: state unknown until a record says where it is (the rejected one: active);
    # lost from 40 to 30 min ago; unconfigured since the new process.
    assert spent == {"active": 5.0 + 10.0, "unknown": 5.0, "process lost": 10.0, "unconfigured": 30.0}
    assert timeline.availability == pytest.approx(15 / 60)
    assert timeline.availability_of_known == pytest.approx(15 / 55)  # 5 minutes unknown


def test_node_found_inside_the_window(robot):
    node = make_node(robot, state=IN, changed=10, first_seen=30)
    record(node, 10, U, IN)
    timeline = tl.node_timeline(node, "hour", now=NOW)
    # Its state read on discovery is not recorded; the first record's "from" state tells it.
    assert minutes(timeline) == {tl.NOT_SEEN: 30.0, "unconfigured": 20.0, "inactive": 10.0}
    assert timeline.availability == 0.0


def test_availability_counts_from_when_the_node_was_first_seen(robot):
    """Issue 26: a node found six minutes ago and active for five of them had 0.35 % over a day
    (5 of 1,440 minutes): the time before it existed counted as not available."""
    node = make_node(robot, state=A, changed=5, first_seen=6, desired="active")
    record(node, 5, U, A)
    timeline = tl.node_timeline(node, "day", now=NOW)
    assert minutes(timeline) == {tl.NOT_SEEN: 24 * 60 - 6.0, "unconfigured": 1.0, "active": 5.0}
    assert timeline.availability == pytest.approx(5 / 6)
    assert timeline.observed_seconds == 6 * 60 and timeline.counted_from == ago(6)
    body = timeline.as_dict()
    assert body["availability_percent"] == pytest.approx(83.333, abs=0.001)
    assert body["counted_from"] == ago(6).isoformat()
    # Seen before the window: counted over all of it, as before.
    old = make_node(robot, name="/old", state=A, changed=30, desired="active")
    record(old, 120, U, IN)
    record(old, 30, IN, A)
    older = tl.node_timeline(old, "hour", now=NOW)
    assert older.counted_from is None and older.availability == pytest.approx(0.5)
    # Not seen at all in the window: no availability (rather than 0 %), and not in the robot's mean.
    make_node(robot, name="/pinned", state=sm.UNKNOWN, first_seen=None, last_seen=None, alive=False,
              desired="active")
    timelines = robot_timeline_of(robot, "day", now=NOW)
    by_name = {t.node.name: t for t in timelines.nodes}
    assert by_name["/pinned"].availability is None
    assert timelines.availability == pytest.approx((5 / 6 + by_name["/old"].availability) / 2)


def test_node_found_inside_the_window_without_records_is_in_its_current_state(robot):
    node = make_node(robot, state=U, changed=30, first_seen=30)
    timeline = tl.node_timeline(node, "hour", now=NOW)
    assert minutes(timeline) == {tl.NOT_SEEN: 30.0, "unconfigured": 30.0}


def test_a_change_the_records_do_not_explain_is_unknown_not_guessed(robot):
    node = make_node(robot, state=IN, changed=10)
    record(node, 70, IN, A)
    record(node, 10, U, IN)  # from unconfigured: its process was restarted at some unknown time
    timeline = tl.node_timeline(node, "hour", now=NOW)
    assert minutes(timeline) == {"unknown": 50.0, "inactive": 10.0}
    assert timeline.unknown_seconds == 50 * 60 and timeline.availability == 0.0


def test_the_last_state_fact_without_record_ends_the_timeline(robot):
    node = make_node(robot, state=U, changed=15)  # read after a restart, not recorded
    record(node, 90, IN, A)
    timeline = tl.node_timeline(node, "hour", now=NOW)
    assert minutes(timeline) == {"unknown": 45.0, "unconfigured": 15.0}
    # A transition state follows from the state before it: no unknown stretch.
    busy = make_node(robot, name="/camera", state=sm.ACTIVATING, changed=15)
    record(busy, 90, U, IN)
    assert minutes(tl.node_timeline(busy, "hour", now=NOW)) == {"inactive": 45.0, "activating": 15.0}


def test_a_gone_node_is_gone_since_it_was_last_seen(robot):
    node = make_node(robot, state=A, changed=120, alive=False, last_seen=15)
    record(node, 120, IN, A)
    timeline = tl.node_timeline(node, "hour", now=NOW)
    assert minutes(timeline) == {"active": 45.0, tl.GONE: 15.0}
    assert "Not seen since 2026-11-23 11:45:00 UTC." in timeline.notes
    lost = make_node(robot, name="/camera", state=A, changed=120, alive=False, last_seen=90, gone_reason="unreachable")
    assert minutes(tl.node_timeline(lost, "hour", now=NOW)) == {tl.UNREACHABLE: 60.0}


def away(node: ManagedNode, gone: float, back: float | None, reason: str = "") -> NodeAbsence:
    return NodeAbsence.objects.create(node=node, gone_at=ago(gone), back_at=ago(back) if back is not None else None,
                                      reason=reason)


def test_past_absences_are_drawn_and_counted(robot):
    node = make_node(robot, state=A, changed=10)
    record(node, 120, IN, A)
    away(node, 200, 70)  # before the window: not drawn, not counted
    away(node, 50, 40, "unreachable")
    away(node, 30, 20, "process_lost")
    record(node, 10, IN, A)  # after its return it was found inactive, and activated
    timeline = tl.node_timeline(node, "hour", now=NOW)
    assert [(s.state, round((s.end - s.start).total_seconds() / 60)) for s in timeline.segments] == [
        ("active", 10), (tl.UNREACHABLE, 10), ("unknown", 10), (tl.LOST, 10), ("inactive", 10), ("active", 10)]
    # back from unreachable at -40: its state was read, not recorded, and the next fact (lost at
    # -30) says nothing about it; back from lost at -20: the record at -10 starts from inactive.
    assert timeline.absences == 2 and timeline.as_dict()["absences"] == 2
    assert timeline.availability == pytest.approx(20 / 60)


def test_an_absence_from_before_the_window_and_one_still_open(robot):
    node = make_node(robot, state=A, changed=100, alive=False, last_seen=15)
    away(node, 90, 45)
    record(node, 30, U, IN)
    away(node, 15, None)
    timeline = tl.node_timeline(node, "hour", now=NOW)
    assert minutes(timeline) == {tl.GONE: 30.0, "unconfigured": 15.0, "inactive": 15.0}
    assert timeline.absences == 1  # the one that began inside the window
    assert "Not seen since 2026-11-23 11:45:00 UTC." in timeline.notes
    shared = robot_timeline_of(robot, "hour", now=NOW).nodes[0]
    assert minutes(shared) == minutes(timeline) and shared.absences == 1


def test_absences_are_read_up_to_their_cap(robot):
    node = make_node(robot, state=A, changed=120)
    for i in range(10):
        away(node, 55 - 5 * i, 53 - 5 * i)
    timeline = tl.node_timeline(node, "hour", now=NOW, absence_cap=4)
    assert timeline.cut_before == ago(55 - 5 * 6) and timeline.segments[0].state == tl.NOT_READ
    assert minutes(timeline)[tl.GONE] == 8.0 and timeline.absences == 4


def test_no_records_and_state_older_than_the_window(robot):
    node = make_node(robot, state=A, changed=60 * 24 * 3, desired="")
    timeline = tl.node_timeline(node, "day", now=NOW)
    assert minutes(timeline) == {"active": 24 * 60.0}
    assert timeline.availability is None and timeline.as_dict()["availability_percent"] is None
    never = make_node(robot, name="/pinned", state=sm.UNKNOWN, first_seen=None, last_seen=None, alive=False)
    assert minutes(tl.node_timeline(never, "hour", now=NOW)) == {tl.NOT_SEEN: 60.0}


def test_reads_at_most_the_cap_and_says_what_was_cut(robot):
    node = make_node(robot, state=A, changed=1)
    record(node, 300, U, IN)
    for i in range(30):  # every 2 minutes: activate, deactivate, ...
        record(node, 59 - 2 * i, IN if i % 2 == 0 else A, A if i % 2 == 0 else IN)
    timeline = tl.node_timeline(node, "hour", now=NOW, cap=10)
    assert timeline.rows_read == 10 and timeline.cut_before == ago(59 - 2 * 20)
    assert timeline.outcomes == {"succeeded": 30}  # counted over the whole window
    assert timeline.segments[0].state == tl.NOT_READ and timeline.segments[0].end == ago(19)
    assert minutes(timeline)[tl.NOT_READ] == 41.0
    assert any("Only the newest 10 records" in note for note in timeline.notes)


def test_robot_timeline_sums_its_nodes(robot):
    lidar = make_node(robot, "/lidar", state=A, changed=30)
    camera = make_node(robot, "/camera", state=IN, changed=60 * 5, desired="")
    record(lidar, 120, U, IN)
    record(lidar, 30, IN, A)
    record(lidar, 20, A, A, "failed")
    record(camera, 300, U, IN)
    other = Robot.objects.create(name="tl-other", domain_id=62)
    record(make_node(other, "/lidar"), 10, IN, A, "failed")  # another robot's: not counted
    timelines = robot_timeline_of(robot, "hour", now=NOW)
    by_name = {t.node.name: t for t in timelines.nodes}
    assert minutes(by_name["/lidar"]) == {"inactive": 30.0, "active": 30.0}
    assert minutes(by_name["/camera"]) == {"inactive": 60.0}
    assert timelines.availability == pytest.approx(0.5)  # only /lidar has a desired state
    assert timelines.failures == 1 and timelines.restarts == 0
    body = timelines.as_dict()
    assert body["availability_percent"] == 50.0 and len(body["nodes"]) == 2


def test_every_query_of_a_timeline_runs_on_an_index(robot):
    node = make_node(robot, state=A, changed=30)
    for i in range(40):
        record(node, 600 - 10 * i, IN, A)
    record(node, 5, A, A, "failed")  # a mark: its reason read by primary key
    plans = []
    with CaptureQueriesContext(connection) as captured:
        tl.node_timeline(node, "hour", now=NOW)
        robot_timeline_of(robot, "day", now=NOW)
    with connection.cursor() as cursor:
        for query in captured.captured_queries:
            if any(table in query["sql"] for table in ("audit_transitionrecord", "fleet_nodeabsence",
                                                          "fleet_gatewayoutage")):
                cursor.execute("EXPLAIN QUERY PLAN " + query["sql"])
                plans.append((query["sql"], " | ".join(str(row[-1]) for row in cursor.fetchall())))
    # node: window, absences, before, counts, marks' reasons, gateway outages; robot: its nodes
    # (with their last record before), window, absences, counts, marks' reasons, gateway outages
    assert len(plans) == 12, plans
    for sql, plan in plans:
        assert "SCAN audit_transitionrecord" not in plan and "SCAN U0" not in plan, (sql, plan)
        assert "SCAN fleet_nodeabsence" not in plan and "SCAN fleet_gatewayoutage" not in plan, (sql, plan)
        assert any(index in plan for index in ("INDEX audit_", "INDEX absence_", "INDEX outage_",
                                               "USING INTEGER PRIMARY KEY")), (sql, plan)
    counts = [plan for sql, plan in plans if "COUNT(" in sql]
    assert len(counts) == 2 and all("COVERING INDEX audit_" in plan for plan in counts), counts
