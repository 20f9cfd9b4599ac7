"""What a gateway reports becomes rows, once: ingest.facts.apply_facts, the one writer used by
the ingest process and by the request path alike."""
from __future__ import annotations

from datetime import datetime, timedelta, timezone

import pytest

from lifecycle_site.audit.models import ParameterRecord, TransitionRecord
from lifecycle_site.fleet.models import Gateway, GroupRun, ManagedNode, NodeAbsence, Robot
from lifecycle_site.fleet.serializers import node_dict
from lifecycle_site.ingest.fact_context import Hints
from lifecycle_site.ingest.facts import apply_facts
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm
from tests.conftest import make_user
from tests.gateway_part import GatewayPart


@pytest.fixture
def cell(db) -> tuple[GatewayPart, Robot]:
    gateway = Gateway.objects.create(name="cell-f")
    return GatewayPart("cell-f"), Robot.objects.create(name="facts-agv", domain_id=40, gateway=gateway)


def node(robot: Robot, name: str = "/lidar") -> ManagedNode:
    return ManagedNode.objects.get(robot=robot, name=name)


def test_the_same_transition_fact_twice_makes_one_record(cell):
    part, robot = cell
    user = make_user("fact-operator", "operator")
    seen = part.fact(protocol.NODE_SEEN, robot=robot.name, node="/lidar")
    done = part.transition(robot.name, "/lidar", sm.CONFIGURE, "configure", sm.UNCONFIGURED, sm.INACTIVE,
                           user_id=user.pk, source="dashboard")
    first = apply_facts("cell-f", [seen, done])
    again = apply_facts("cell-f", [seen, done])

    record = TransitionRecord.objects.get()
    assert first.created == [record] and again.created == []
    assert first.transition_record([done]) == again.transition_record([done]) == record
    assert record.fact_id == done["id"] and record.node == node(robot) and record.robot == robot
    assert (record.transition_label, record.start_state_label, record.goal_state_label, record.result_state_label) \
        == ("configure", "unconfigured", "inactive", "inactive")
    assert (record.requested_by, record.requested_by_name, record.source) == (user, "fact-operator", "dashboard")
    assert record.duration_ms == 0.0 and record.as_dict()["node_id"] == "facts-agv.lidar"


def test_parameter_facts_are_audited_once_with_their_time(cell):
    part, robot = cell
    changed = part.vouch(part.fact(protocol.PARAMETER, robot=robot.name, node="/lidar", name="rate", old=10, new=20,
                                   outcome="succeeded", reason="", source="api", user_id=999_999))
    apply_facts("cell-f", [part.fact(protocol.NODE_SEEN, robot=robot.name, node="/lidar"), changed, changed])
    record = ParameterRecord.objects.get()
    assert (record.name, record.old_value, record.new_value, record.outcome) == ("rate", 10, 20, "succeeded")
    assert record.at == datetime.fromisoformat(changed["at"]) and record.node == node(robot)
    assert record.requested_by is None and record.requested_by_name == ""  # no such user


def test_nodes_come_and_go_and_a_late_state_never_wins(cell):
    part, robot = cell
    seen = part.fact(protocol.NODE_SEEN, robot=robot.name, node="/lidar")
    inactive = part.fact(protocol.NODE_STATE, robot=robot.name, node="/lidar", state_id=sm.INACTIVE)
    active = part.fact(protocol.NODE_STATE, robot=robot.name, node="/lidar", state_id=sm.ACTIVE)
    apply_facts("cell-f", [seen, active])
    apply_facts("cell-f", [inactive])  # applied late (the ingest process behind the request path)
    lidar = node(robot)
    assert (lidar.alive, lidar.state_label, lidar.first_seen) == (True, "active", datetime.fromisoformat(seen["at"]))

    apply_facts("cell-f", [part.fact(protocol.NODE_GONE, robot=robot.name, node="/lidar")])
    assert not node(robot).alive and node(robot).state_label == "active"  # the last known state stays

    camera = part.fact(protocol.NODE_STATE, robot=robot.name, node="/camera", state_id=sm.UNCONFIGURED)
    listing = part.fact(protocol.ROBOT_NODES, robot=robot.name, nodes=["/camera", "/planner"])
    apply_facts("cell-f", [camera, listing])
    states = {n.name: (n.alive, n.state_label) for n in robot.nodes.all()}
    assert states == {"/lidar": (False, "active"), "/camera": (True, "unconfigured"), "/planner": (True, "unknown")}


def test_absences_are_recorded_once_from_gone_to_back(cell):
    part, robot = cell
    seen = part.fact(protocol.NODE_SEEN, robot=robot.name, node="/lidar")
    pinned = ManagedNode.objects.create(robot=robot, name="/pinned")  # watched by name, never seen
    gone = part.fact(protocol.NODE_GONE, robot=robot.name, node="/lidar", reason="unreachable")
    lost = part.fact(protocol.NODE_GONE, robot=robot.name, node="/lidar", reason=protocol.PROCESS_LOST)
    never = part.fact(protocol.NODE_GONE, robot=robot.name, node="/pinned")
    apply_facts("cell-f", [seen, gone, lost, never])
    apply_facts("cell-f", [gone])  # applied twice
    absence = NodeAbsence.objects.get()  # one, open, with the newer reason; none for /pinned
    assert (absence.node, absence.gone_at, absence.back_at, absence.reason) == (
        node(robot), datetime.fromisoformat(gone["at"]), None, protocol.PROCESS_LOST)
    assert not pinned.absences.exists()

    back = part.fact(protocol.NODE_SEEN, robot=robot.name, node="/lidar")
    apply_facts("cell-f", [back, back])
    absence.refresh_from_db()
    assert absence.back_at == datetime.fromisoformat(back["at"])

    # A robot's node list without a running node opens its absence; with it again, closes it.
    camera = part.fact(protocol.NODE_SEEN, robot=robot.name, node="/camera")
    without = part.fact(protocol.ROBOT_NODES, robot=robot.name, nodes=["/camera"])
    apply_facts("cell-f", [camera, without])
    opened = NodeAbsence.objects.get(back_at__isnull=True)
    assert (opened.node.name, opened.gone_at, opened.reason) == ("/lidar", datetime.fromisoformat(without["at"]), "")
    again = part.fact(protocol.ROBOT_NODES, robot=robot.name, nodes=["/camera", "/lidar"])
    apply_facts("cell-f", [again])
    assert not NodeAbsence.objects.filter(back_at__isnull=True).exists()
    assert NodeAbsence.objects.count() == 2


def test_runs_follow_their_facts_but_never_come_back_from_done(cell):
    part, robot = cell
    run = GroupRun.objects.create(id=protocol.new_id(), robot=robot, operation="bringup")
    step = {"node": "/lidar", "outcome": "succeeded", "steps": []}
    apply_facts("cell-f", [part.fact(protocol.RUN, run_id=run.id, robot=robot.name, status="running", message="",
                                     results=[step], started=part.tick(), finished=None)])
    run.refresh_from_db()
    assert (run.status, run.results, run.started is not None) == ("running", [step], True)
    done = part.fact(protocol.RUN, run_id=run.id, robot=robot.name, status="succeeded", message="1 succeeded",
                     results=[step], started=None, finished=part.tick())
    late = part.fact(protocol.RUN, run_id=run.id, robot=robot.name, status="running", message="", results=[],
                     started=None, finished=None)
    apply_facts("cell-f", [done, late])
    run.refresh_from_db()
    assert (run.status, run.message, run.results) == ("succeeded", "1 succeeded", [step])

    recovery = part.fact(protocol.RUN, run_id=protocol.new_id(), robot=robot.name, status="queued", message="",
                         results=[], started=None, finished=None, operation="recover", only_nodes=["/lidar"],
                         source="recovery", policy="stop", node_timeout=5.0)
    unknown = part.fact(protocol.RUN, run_id="nope", robot=robot.name, status="running", results=[],
                        started=None, finished=None)
    applied = apply_facts("cell-f", [recovery, unknown])
    assert applied.rejected == 1  # a run the site never heard of, without its spec
    made = GroupRun.objects.get(pk=recovery["run_id"])
    assert (made.operation, made.only_nodes, made.source, made.status) == ("recover", ["/lidar"], "recovery", "queued")

    # The nodes of one restarted process come back as one recovery; a bounded one.
    several = part.fact(protocol.RUN, run_id=protocol.new_id(), robot=robot.name, status="queued", message="",
                        results=[], started=None, finished=None, operation="recover",
                        only_nodes=["/base", "/lidar", "/base"], source="recovery", policy="continue", node_timeout=5.0)
    too_many = part.fact(protocol.RUN, run_id=protocol.new_id(), robot=robot.name, status="queued", message="",
                         results=[], started=None, finished=None, operation="recover",
                         only_nodes=[f"/n{i}" for i in range(2001)], source="recovery", node_timeout=5.0)
    none = part.fact(protocol.RUN, run_id=protocol.new_id(), robot=robot.name, status="queued", message="",
                     results=[], started=None, finished=None, operation="recover", only_nodes=[], source="recovery")
    assert apply_facts("cell-f", [several, too_many, none]).rejected == 2
    made = GroupRun.objects.get(pk=several["run_id"])
    assert (made.only_nodes, made.policy) == (["/base", "/lidar"], "continue")


def test_an_end_reported_after_the_sites_verdict_leaves_the_run_as_the_site_ended_it(cell):
    part, robot = cell
    verdict = "the gateway cell-f has been silent since 2026-11-25 20:14:36 UTC, so the run could not finish"
    run = GroupRun.objects.create(id=protocol.new_id(), robot=robot, operation="bringup", status="failed",
                                  message=verdict)
    step = {"node": "/lidar", "outcome": "succeeded", "steps": [{"transition": "activate", "outcome": "succeeded"}]}
    late = part.fact(protocol.RUN, run_id=run.id, robot=robot.name, status="succeeded", message="1 succeeded",
                     results=[step], started=None, finished=part.tick())
    apply_facts("cell-f", [late])
    apply_facts("cell-f", [late])  # applied again (ingest after a crash): said once
    run.refresh_from_db()
    assert run.status == "failed"
    assert run.message == f"{verdict}; after this verdict the gateway reported: succeeded (1 succeeded)"
    assert run.results == [step]  # what the gateway did, as it reported it


def test_a_gateway_restart_fails_the_runs_it_no_longer_knows(cell):
    part, robot = cell
    running = GroupRun.objects.create(id=protocol.new_id(), robot=robot, operation="bringup", status="running")
    finished = GroupRun.objects.create(id=protocol.new_id(), robot=robot, operation="pause", status="succeeded")
    other = Robot.objects.create(name="other-agv", domain_id=41, gateway=Gateway.objects.create(name="cell-g"))
    elsewhere = GroupRun.objects.create(id=protocol.new_id(), robot=other, operation="bringup", status="running")
    restarted = GatewayPart("cell-f")
    restarted.clock = datetime.now(timezone.utc) + timedelta(seconds=1)
    apply_facts("cell-f", [restarted.fact(protocol.GATEWAY_STARTED)])
    statuses = {r.pk: (r.status, r.message) for r in GroupRun.objects.all()}
    message = f"the gateway cell-f restarted while it ran (instance {restarted.instance}); its last results are kept"
    assert statuses[running.pk] == ("failed", message)
    assert statuses[finished.pk][0] == "succeeded" and statuses[elsewhere.pk][0] == "running"


def test_a_gateway_cannot_write_for_another_gateways_robots_and_bad_facts_fail_alone(cell):
    part, robot = cell
    other = Robot.objects.create(name="other-agv", domain_id=41, gateway=Gateway.objects.create(name="cell-g"))
    applied = apply_facts("cell-f", [
        part.fact(protocol.NODE_SEEN, robot=other.name, node="/lidar"),
        part.transition(other.name, "/lidar", sm.CONFIGURE, "configure", 1, 2),
        {**part.fact(protocol.NODE_SEEN, robot=robot.name, node="/lidar"), "gateway": "cell-g"},
        part.fact("node.exploded", robot=robot.name),
        part.fact(protocol.NODE_SEEN, robot=robot.name, node=["/not", "a name"]),
        part.fact(protocol.NODE_STATE, robot=robot.name, node="/lidar", state_id="active"),
        part.fact(protocol.NODE_SEEN, robot=robot.name, node="/lidar"),  # this one is fine
    ])
    assert applied.rejected == 6
    assert not other.nodes.exists() and not TransitionRecord.objects.exists()
    assert list(robot.nodes.values_list("name", flat=True)) == ["/lidar"]


def test_facts_about_robots_the_gateway_does_not_own_are_refused_and_never_stored(cell):
    """F5: names are matched exactly (no case folding, no trimming, no look-alikes); a robot
    that does not exist (or no longer does) is not the gateway's either."""
    part, robot = cell
    other = Robot.objects.create(name="agv-1", domain_id=41, gateway=Gateway.objects.create(name="cell-other"))
    names = [other.name, "agv-3", f"{robot.name} ", robot.name.upper(), robot.name.replace("a", "\u0430"),
             f"{robot.name}\u200b", '=HYPERLINK("http://evil")']
    facts = [part.transition(name, "/lidar", sm.ACTIVATE, "activate", 2, 3) for name in names]
    facts += [part.fact(protocol.NODE_STATE, robot=name, node="/lidar", state_id=sm.ACTIVE) for name in names]
    applied = apply_facts("cell-f", facts)
    assert applied.rejected == len(facts) and applied.accepted == []
    assert not TransitionRecord.objects.exists() and not ManagedNode.objects.exists()


def test_a_replys_facts_with_the_request_paths_hints_cost_seven_queries(cell, django_assert_num_queries):
    """BEGIN, the node's state, the record's fact id, where the node's records leave it and the
    insert, the node's audited state (the chain, ingest/state_chain.py), COMMIT: no savepoint per
    fact, no second read of the node, robot or user the request already holds."""
    part, robot = cell
    user = make_user("hint-operator", "operator")
    apply_facts("cell-f", [part.fact(protocol.NODE_SEEN, robot=robot.name, node="/lidar")])
    lidar = ManagedNode.objects.select_related("robot__gateway").get(robot=robot, name="/lidar")
    reply = [part.fact(protocol.NODE_STATE, robot=robot.name, node="/lidar", state_id=sm.INACTIVE),
             part.transition(robot.name, "/lidar", sm.CONFIGURE, "configure", 1, 2, user_id=user.pk)]
    with django_assert_num_queries(7):
        applied = apply_facts("cell-f", reply, Hints(lidar, user))
    record = applied.transition_record(reply)
    assert (record.requested_by_id, record.requested_by_name, record.node_id) == (user.pk, "hint-operator", lidar.pk)
    assert node(robot).state_label == "inactive"


def test_hints_about_one_robot_still_let_facts_name_the_gateways_other_robots(cell):
    part, robot = cell
    second = Robot.objects.create(name="facts-agv-2", domain_id=42, gateway=robot.gateway)
    outsider = Robot.objects.create(name="not-mine", domain_id=43, gateway=Gateway.objects.create(name="cell-h"))
    apply_facts("cell-f", [part.fact(protocol.NODE_SEEN, robot=robot.name, node="/lidar")])
    lidar = ManagedNode.objects.select_related("robot__gateway").get(robot=robot, name="/lidar")
    applied = apply_facts("cell-f", [
        part.fact(protocol.NODE_SEEN, robot=second.name, node="/camera"),
        part.fact(protocol.NODE_SEEN, robot=outsider.name, node="/camera"),
    ], Hints(lidar))
    assert applied.rejected == 1
    assert list(second.nodes.values_list("name", flat=True)) == ["/camera"] and not outsider.nodes.exists()


def test_a_lost_process_and_its_new_instance_move_the_nodes_process_status(cell):
    part, robot = cell
    apply_facts("cell-f", [part.fact(protocol.NODE_SEEN, robot=robot.name, node="/lidar"),
                           part.fact(protocol.NODE_STATE, robot=robot.name, node="/lidar", state_id=sm.ACTIVE)])
    lost_at = datetime.fromisoformat(part.tick())  # the gateway's own time of the loss
    gone = part.fact(protocol.NODE_GONE, robot=robot.name, node="/lidar", reason=protocol.PROCESS_LOST,
                     since=lost_at.isoformat())
    record = part.transition(robot.name, "/lidar", None, "", sm.ACTIVE, None, outcome=protocol.PROCESS_LOST,
                             source="external", error="The process of /lidar on facts-agv exited")
    record["transition_id"], record["result_state"] = None, None
    apply_facts("cell-f", [gone, record])
    lidar = node(robot)
    assert (lidar.alive, lidar.gone_reason, lidar.process_status, lidar.process_since) == (
        False, "process_lost", "lost", lost_at)
    assert node_dict(lidar)["process"] == {"status": "lost", "since": lost_at.isoformat()}
    assert TransitionRecord.objects.get().as_dict()["outcome"] == "process_lost"
    # Back with the same process (it only left the graph for a moment): alive, not "lost".
    apply_facts("cell-f", [part.fact(protocol.NODE_SEEN, robot=robot.name, node="/lidar")])
    assert node_dict(node(robot))["process"] == {"status": "", "since": None}

    back = part.fact(protocol.NODE_SEEN, robot=robot.name, node="/lidar")
    restarted = part.transition(robot.name, "/lidar", None, "", None, sm.UNCONFIGURED,
                                outcome=protocol.PROCESS_RESTARTED, source="external", error="new instance")
    restarted["transition_id"], restarted["start_state"] = None, None
    apply_facts("cell-f", [back, restarted])
    lidar = node(robot)
    since = datetime.fromisoformat(restarted["completed_at"])
    assert (lidar.alive, lidar.gone_reason, lidar.process_status, lidar.process_since) == (
        True, "", "restarted", since)
    assert node_dict(lidar)["process"] == {"status": "restarted", "since": since.isoformat()}
    # An older loss applied late does not undo the restart.
    apply_facts("cell-f", [part.fact(protocol.NODE_GONE, robot=robot.name, node="/lidar", reason=protocol.PROCESS_LOST,
                                     since=(lost_at - timedelta(seconds=5)).isoformat())])
    assert node(robot).process_status == "restarted"
    outcomes = sorted(TransitionRecord.objects.values_list("outcome", flat=True))
    assert outcomes == ["process_lost", "process_restarted"]


def test_a_gateway_cannot_put_a_change_on_a_users_name_or_the_dashboards(cell):
    """F5: a fact's user and source count only with the site's grant for the request it answers;
    on its own a gateway may say "external" or "recovery", with nobody's name. What it claims
    beyond is not taken (and said in the record)."""
    part, robot = cell
    admin = make_user("fact-admin", "admin")
    forged = part.transition(robot.name, "/lidar", sm.ACTIVE_SHUTDOWN, "shutdown", 3, 4, source="external")
    forged.update(source="dashboard", user_id=admin.pk)  # as a stranger would send it: no grant
    borrowed = part.transition(robot.name, "/lidar", sm.CONFIGURE, "configure", 1, 2, source="api", user_id=admin.pk)
    borrowed["user_id"] = make_user("fact-viewer", "viewer").pk  # a real grant, another user put in
    unnamed_external = part.transition(robot.name, "/lidar", sm.ACTIVATE, "activate", 2, 3, source="external")
    unnamed_external["user_id"] = admin.pk
    honest = part.transition(robot.name, "/lidar", sm.ACTIVATE, "activate", 2, 3, source="external")
    vouched = part.transition(robot.name, "/lidar", sm.DEACTIVATE, "deactivate", 3, 2, source="dashboard",
                              user_id=admin.pk)
    applied = apply_facts("cell-f", [forged, borrowed, unnamed_external, honest, vouched])
    assert applied.rejected == 0  # every change that reached the robot stays on record ...
    kept = {(r.transition_label, r.source, r.requested_by_name, r.error) for r in TransitionRecord.objects.all()}
    said = "the site sent it no such request)"
    assert kept == {  # ... but on nobody's name the site did not vouch for
        ("shutdown", "external", "", f" (the gateway said source dashboard, user #{admin.pk}; {said}"),
        ("configure", "external", "", f" (the gateway said source api, user #{borrowed['user_id']}; {said}"),
        ("activate", "external", "", f" (the gateway said source external, user #{admin.pk}; {said}"),
        ("activate", "external", "", ""),
        ("deactivate", "dashboard", "fact-admin", ""),
    }


def test_a_steps_user_is_the_runs_and_a_gateway_may_start_only_recoveries(cell):
    part, robot = cell
    operator = make_user("fact-run-operator", "operator")
    run = GroupRun.objects.create(id=protocol.new_id(), robot=robot, operation="bringup", status="running",
                                  source="dashboard", requested_by=operator)
    step = part.transition(robot.name, "/lidar", sm.CONFIGURE, "configure", 1, 2, source="external", run_id=run.id)
    other_robot = Robot.objects.create(name="facts-arm", domain_id=44, gateway=Gateway.objects.get(name="cell-f"))
    foreign = part.transition(other_robot.name, "/lidar", sm.CONFIGURE, "configure", 1, 2, source="external",
                              run_id=run.id)  # a run of another robot
    started = part.fact(protocol.RUN, run_id=protocol.new_id(), robot=robot.name, status="running",
                        operation="shutdown", only_nodes=[], source="dashboard")
    recovery = part.fact(protocol.RUN, run_id=protocol.new_id(), robot=robot.name, status="running",
                         operation="recover", only_nodes=["/lidar"], source="recovery")
    applied = apply_facts("cell-f", [step, foreign, started, recovery])
    assert applied.rejected == 2
    record = TransitionRecord.objects.get()
    assert (record.source, record.requested_by_name, record.run_id) == ("dashboard", "fact-run-operator", run.id)
    assert set(GroupRun.objects.values_list("operation", flat=True)) == {"bringup", "recover"}


def test_a_grant_makes_one_record_of_what_it_was_given_for(cell):
    """Review of issue 25: a grant seen once cannot be replayed on new fact ids, nor on another
    transition, to put more changes on the same user's name."""
    part, robot = cell
    user = make_user("grant-operator", "operator")
    honest = part.transition(robot.name, "/lidar", sm.CONFIGURE, "configure", 1, 2, user_id=user.pk)
    replayed = {**honest, "id": protocol.new_id()}
    other = {**honest, "id": honest["request_id"], "transition_id": sm.ACTIVE_SHUTDOWN, "transition_label": "shutdown"}
    apply_facts("cell-f", [honest])
    apply_facts("cell-f", [replayed, other])
    named = TransitionRecord.objects.filter(requested_by_name="grant-operator")
    assert [r.transition_label for r in named] == ["configure"]
    assert TransitionRecord.objects.filter(fact_id=replayed["id"], source="external").exists()


def test_a_step_takes_the_runs_user_only_while_the_run_is_under_way_and_for_its_nodes(cell):
    part, robot = cell
    operator = make_user("window-operator", "operator")
    run = GroupRun.objects.create(id=protocol.new_id(), robot=robot, operation="restart", status="running",
                                  source="dashboard", requested_by=operator, only_nodes=["/lidar"])
    inside = part.transition(robot.name, "/lidar", sm.CONFIGURE, "configure", 1, 2, source="external", run_id=run.id)
    other_node = part.transition(robot.name, "/camera", sm.CONFIGURE, "configure", 1, 2, source="external",
                                 run_id=run.id)
    later = part.transition(robot.name, "/lidar", sm.ACTIVATE, "activate", 2, 3, source="external", run_id=run.id)
    later["requested_at"] = (datetime.now(timezone.utc) + timedelta(minutes=30)).isoformat()
    GroupRun.objects.filter(pk=run.pk).update(status="succeeded", finished=datetime.now(timezone.utc))
    apply_facts("cell-f", [inside, other_node, later])
    by = {r.fact_id: (r.source, r.requested_by_name) for r in TransitionRecord.objects.all()}
    assert by[inside["id"]] == ("dashboard", "window-operator")
    assert by[other_node["id"]] == by[later["id"]] == ("external", "")
