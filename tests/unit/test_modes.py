"""Robot modes without a gateway: what a mode may say (lifecycle_site/modes/definitions.py), which
parameter facts of a mode's run carry the operator's name (only the mode's values, on its nodes:
gateway_link/attribution.py), and how drift is worked out from the nodes and the records
(lifecycle_site/modes/drift.py). Applying on real nodes: tests/integration/test_modes.py."""
from __future__ import annotations

import uuid
from datetime import timedelta
from ipaddress import ip_network

import pytest
from django.utils import timezone

from lifecycle_site.alerts import conditions
from lifecycle_site.alerts.models import Rule
from lifecycle_site.audit.models import ParameterRecord
from lifecycle_site.fleet.models import Gateway, GroupRun, ManagedNode, Robot
from lifecycle_site.gateway_link.gateway_config import build_config
from lifecycle_site.ingest.facts import apply_facts
from lifecycle_site.modes import definitions, drift, yaml_files
from lifecycle_site.modes.models import CurrentMode, Mode, TopicRate
from ros_gateway import mode_plan
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm
from tests.conftest import client_of, make_user
from tests.gateway_part import GatewayPart

PLAN = {"mode": "mapping", "targets": {"/lidar": "active", "/cam": None},
        "parameters": {"/lidar": {"scan_rate_hz": 12.0}}}


def test_a_mode_definition_is_checked_and_every_problem_is_said():
    assert definitions.problems({"/lidar": {"state": "active", "parameters": {"rate": 2.5, "names": ["a", "b"]}},
                                 "/cam": {"state": None}, "/arm/grip": {}}) == []
    found = definitions.problems({
        "lidar": {}, "/a": {"state": "finalized"}, "/b": {"state": "active", "colour": "red"},
        "/c": {"parameters": {"x": float("nan"), "y": [1, "two"], "z": {"deep": 1}, "9bad": 1}},
    })
    assert found == [
        "'lidar' is not a fully qualified node name (such as /lidar_driver).",
        "/a: 'finalized' is not a state a mode can ask for; use unconfigured, inactive, active or null (left alone).",
        "/b: give only state and parameters.",
        "/c: x is not a number, true/false, text or list of one of these.",
        "/c: y is a list must hold values of one kind (true/false, numbers or texts).",
        "/c: z is not a number, true/false, text or list of one of these.",
        "/c: '9bad' is not a parameter name.",
    ]
    assert definitions.problems([]) != [] and definitions.problems({f"/n{i}": {} for i in range(501)}) != []


def test_the_gateway_takes_a_plan_with_a_target_for_every_node_and_nothing_else():
    targets, parameters = mode_plan.parse(PLAN, ["/lidar", "/cam"])
    assert targets == {"/lidar": sm.ACTIVE, "/cam": None} and parameters == {"/lidar": {"scan_rate_hz": 12.0}}
    for bad, why in (({**PLAN, "targets": {"/lidar": "active"}}, "names no target for /cam"),
                     ({**PLAN, "targets": {"/lidar": "finalized", "/cam": None}}, "'finalized' is not a state"),
                     ({**PLAN, "parameters": {"/other": {"x": 1}}}, "not one of the run's nodes"),
                     ({**PLAN, "targets": ["/lidar"]}, "needs its targets")):
        with pytest.raises(mode_plan.BadPlan, match=why):
            mode_plan.parse(bad, ["/lidar", "/cam"])
    # Down first (in reverse order), then up: a node moves in one of the two phases only.
    assert mode_plan.goes("down", sm.ACTIVE, sm.UNCONFIGURED) and not mode_plan.goes("up", sm.ACTIVE, sm.UNCONFIGURED)
    assert mode_plan.goes("up", sm.UNCONFIGURED, sm.ACTIVE) and not mode_plan.goes("down", sm.INACTIVE, sm.INACTIVE)
    assert mode_plan.goes("up", sm.FINALIZED, sm.ACTIVE)  # the up phase says it cannot


@pytest.fixture
def cell(db) -> tuple[GatewayPart, Robot, GroupRun]:
    gateway = Gateway.objects.create(name="cell-m")
    robot = Robot.objects.create(name="modes-agv", domain_id=41, gateway=gateway)
    user = make_user("mode-operator", "operator")
    run = GroupRun.objects.create(id=uuid.uuid4().hex, robot=robot, operation="mode", only_nodes=["/lidar", "/cam"],
                                  plan=PLAN, requested_by=user, source="dashboard")
    part = GatewayPart("cell-m")
    apply_facts("cell-m", [part.fact(protocol.NODE_SEEN, robot=robot.name, node=n) for n in ("/lidar", "/cam")])
    return part, robot, run


def parameter_fact(part: GatewayPart, robot: Robot, run: GroupRun, node: str, name: str, new) -> dict:
    return part.fact(protocol.PARAMETER, robot=robot.name, node=node, name=name, old=5.0, new=new,
                     outcome="succeeded", reason="", source="dashboard", user_id=run.requested_by_id, run_id=run.id)


def test_only_the_values_of_the_runs_mode_carry_the_operators_name(cell):
    part, robot, run = cell
    apply_facts("cell-m", [
        parameter_fact(part, robot, run, "/lidar", "scan_rate_hz", 12.0),  # the mode's
        parameter_fact(part, robot, run, "/lidar", "scan_rate_hz", 40.0),  # another value
        parameter_fact(part, robot, run, "/lidar", "range_max", 3.0),  # not in the mode
        parameter_fact(part, robot, run, "/cam", "fps", 1.0),  # a node the mode sets nothing on
    ])
    found = {(r.node_name, r.name, r.new_value): (r.source, r.requested_by_name, r.run_id)
             for r in ParameterRecord.objects.all()}
    assert found[("/lidar", "scan_rate_hz", 12.0)] == ("dashboard", "mode-operator", run.id)
    for other in (("/lidar", "scan_rate_hz", 40.0), ("/lidar", "range_max", 3.0), ("/cam", "fps", 1.0)):
        assert found[other][:2] == ("external", ""), other  # kept (it reached a robot), on nobody's name


def test_drift_is_a_node_not_running_in_another_state_or_with_another_value_since_the_mode(cell, client, settings):
    part, robot, run = cell
    mode = Mode.objects.create(name="mapping", nodes={
        "/lidar": {"state": "active", "parameters": {"scan_rate_hz": 12.0, "range_max": 8.0}},
        "/cam": {"state": "inactive"}, "/gone": {"state": "active"}, "/free": {"state": None}})
    mode.robots.add(robot)
    assert drift.summary(robot) == {"mode": None, "drift": []}
    since = timezone.now()
    CurrentMode.objects.create(robot=robot, mode=mode, since=since, run=run)
    ManagedNode.objects.filter(robot=robot).update(alive=True, state_label="inactive", state_id=sm.INACTIVE)
    ManagedNode.objects.filter(robot=robot, name="/lidar").update(state_label="active", state_id=sm.ACTIVE)
    lidar = ManagedNode.objects.get(robot=robot, name="/lidar")
    for name, value, at in (("scan_rate_hz", 3.0, since - timedelta(seconds=5)),  # before the mode: not counted
                            ("scan_rate_hz", 12.0, since + timedelta(seconds=1)),
                            ("range_max", 8.0, since + timedelta(seconds=1)),
                            ("range_max", 20.0, since + timedelta(seconds=2))):  # changed since: drift
        ParameterRecord.objects.create(node=lidar, robot_name=robot.name, node_name="/lidar", name=name,
                                       new_value=value, outcome="observed", source="external", at=at)
    found = drift.summary(robot)
    assert found["mode"] == "mapping" and not found["in_mode"]
    assert [d["message"] for d in found["drift"]] == [
        "/lidar: range_max is 20.0, the mode sets 8.0",
        "/gone is not running (the mode wants it active)",
    ]
    settings.LIFECYCLE_METRICS_ALLOW = [ip_network("127.0.0.1/32")]
    assert 'lifecycle_mode_drift{mode="mapping",robot="modes-agv"} 2.0' in client.get("/metrics").content.decode()
    # The mode's own run sets a value: it counts whatever the gateway's clock said (a record "before"
    # the mode by a skewed clock); a value the mode sets that nothing recorded is not known to be set.
    Mode.objects.filter(pk=mode.pk).update(nodes={**mode.nodes, "/cam": {"state": "inactive",
                                                                          "parameters": {"fps": 10.0}}})
    cam = ManagedNode.objects.get(robot=robot, name="/cam")
    assert ("/cam: fps is 'not set since the mode was applied', the mode sets 10.0"
            in [d["message"] for d in drift.summary(robot)["drift"]])
    ParameterRecord.objects.create(node=cam, robot_name=robot.name, node_name="/cam", name="fps", new_value=10.0,
                                   outcome="succeeded", source="api", at=since - timedelta(seconds=2), run_id=run.id)
    assert not [d for d in drift.summary(robot)["drift"] if d["node"] == "/cam"]
    Mode.objects.filter(pk=mode.pk).update(nodes=mode.nodes)

    from lifecycle_site.dashboard import attention

    strip = [(i["node"], i["label"], i["reason"]) for i in attention._read(gateway_views=[])["items"]]
    assert ("/lidar", "not as mode mapping says", "/lidar: range_max is 20.0, the mode sets 8.0") in strip
    # A new process of the lidar since: its values are its defaults until set again.
    ManagedNode.objects.filter(pk=lidar.pk).update(process_status="restarted",
                                                   process_since=since + timedelta(seconds=3))
    assert [(d["parameter"], d["have"]) for d in drift.summary(robot)["drift"] if d["kind"] == "parameter"] == [
        ("scan_rate_hz", drift.UNKNOWN), ("range_max", drift.UNKNOWN)]


def test_a_node_not_as_the_current_mode_says_needs_attention_in_the_modes_words(cell):
    from lifecycle_site.dashboard import attention

    _, robot, run = cell
    mode = Mode.objects.create(name="charging", nodes={"/cam": {"state": "active"}})
    mode.robots.add(robot)
    CurrentMode.objects.create(robot=robot, mode=mode, since=timezone.now(), run=run)
    ManagedNode.objects.filter(robot=robot, name="/cam").update(
        alive=True, state_label="inactive", state_id=sm.INACTIVE, desired_state="active", last_seen=timezone.now())
    items = attention._read(gateway_views=[])["items"]
    assert [(i["node"], i["label"]) for i in items] == [
        ("/cam", "not as mode charging says: inactive, the mode wants active")]



# A system_modes model file, written from its documented format (a system of parts, each part's
# target "state" or "state.MODE", each node's parameters per mode), with two mistakes in it.
SYSTEM_MODES_FILE = """
# two drives and a lidar, in the form of micro-ROS/system_modes
platform:
  ros__parameters:
    type: system
    parts:
      drives
      lidar_driver
    modes:
      __DEFAULT__:
        drives: active
        lidar_driver: inactive
      MAPPING:
        drives: active.CAREFUL
        lidar_driver: active.DENSE
      PARKED:
        drives: inactive
        lidar_driver: inactive
        lidr_driver: active

drives:
  ros__parameters:
    type: system
    parts: left/wheel right/wheel
    modes:
      __DEFAULT__:
        left/wheel: active
        right/wheel: active
      CAREFUL:
        left/wheel: active.SLOW
        right/wheel: active.SLOW

left/wheel:
  ros__parameters:
    type: node
    modes:
      __DEFAULT__:
        ros__parameters:
          max_speed: 1.0
      SLOW:
        ros__parameters:
          max_speed: 0.3

right/wheel:
  ros__parameters:
    type: node
    modes:
      __DEFAULT__:
        ros__parameters:
          max_speed: 1.0

lidar_driver:
  ros__parameters:
    type: node
    modes:
      __DEFAULT__:
        ros__parameters:
          scan_rate_hz: 5.0
      DENSE:
        ros__parameters:
          scan_rate_hz: 20.0
          num_points: 1440
"""


def test_a_system_modes_model_file_becomes_one_mode_per_system_mode_with_its_problems_named():
    modes, problems = yaml_files.read(SYSTEM_MODES_FILE)
    by_name = {m["name"]: m["nodes"] for m in modes}
    assert list(by_name) == ["platform-default", "platform-mapping", "platform-parked"]
    assert by_name["platform-mapping"] == {
        "/left/wheel": {"state": "active", "parameters": {"max_speed": 0.3}},
        "/right/wheel": {"state": "active"},  # (right/wheel has no SLOW: named below)
        "/lidar_driver": {"state": "active", "parameters": {"scan_rate_hz": 20.0, "num_points": 1440}},
    }
    assert by_name["platform-default"]["/left/wheel"] == {"state": "active", "parameters": {"max_speed": 1.0}}
    # An inactive system takes its parts down with it, without their parameters.
    assert by_name["platform-parked"] == {"/left/wheel": {"state": "inactive"}, "/right/wheel": {"state": "inactive"},
                                          "/lidar_driver": {"state": "inactive"}}
    assert problems == ["right/wheel has no mode SLOW.",
                        "system platform, mode PARKED: lidr_driver is not one of its parts."]


def test_modes_go_out_and_come_back_as_yaml_unchanged():
    nodes = {"/lidar": {"state": "active", "parameters": {"rate": 2.5, "names": ["a", "b"]}}, "/cam": {"state": None}}
    ready = [{"topic": "/scan", "min_hz": 5, "window_s": 2}]
    mode = {"name": "mapping", "description": "for the map", "nodes": nodes, "ready_when": ready}
    assert yaml_files.read(yaml_files.export([mode])) == ([mode], [])
    for bad, why in (("modes: [[1]]", "must be a table"), (": :", "not YAML"), ("a: 1", "holds no modes"),
                     ("x" * (300 * 1024), "over 256 KB")):
        with pytest.raises(yaml_files.FileRefused, match=why):
            yaml_files.read(bad)


@pytest.mark.django_db
def test_an_import_is_shown_before_it_is_saved_and_only_admins_save(operator_client):


    Robot.objects.create(name="yaml-agv", domain_id=43)
    admin = client_of("ada-yaml", "admin")
    body = {"yaml": SYSTEM_MODES_FILE, "robots": ["yaml-agv"], "save": True}
    assert operator_client.post("/api/v1/modes/import", body, content_type="application/json").status_code == 403
    answer = admin.post("/api/v1/modes/import", body, content_type="application/json")
    assert answer.status_code == 200 and not answer.json()["saved"] and len(answer.json()["problems"]) == 2
    fixed = SYSTEM_MODES_FILE.replace("        lidr_driver: active\n", "").replace(
        "          max_speed: 1.0\n\nlidar_driver", "          max_speed: 1.0\n      SLOW:\n        ros__parameters:\n"
        "          max_speed: 0.3\n\nlidar_driver")
    answer = admin.post("/api/v1/modes/import", {**body, "yaml": fixed}, content_type="application/json")
    assert (answer.status_code, answer.json()["problems"], answer.json()["saved"]) == (201, [], True)
    assert sorted(Mode.objects.filter(robots__name="yaml-agv").values_list("name", flat=True)) == [
        "platform-default", "platform-mapping", "platform-parked"]
    exported = admin.get("/api/v1/robots/yaml-agv/modes.yaml")
    assert exported["Content-Disposition"] == 'attachment; filename="yaml-agv-modes.yaml"'
    assert [m["name"] for m in yaml_files.read(exported.content.decode())[0]] == [
        "platform-default", "platform-mapping", "platform-parked"]


@pytest.mark.django_db
def test_the_modes_page_offers_apply_to_operators_files_to_admins_and_polls_quietly(operator_client, viewer_client):
    from django.core.files.uploadedfile import SimpleUploadedFile


    robot = Robot.objects.create(name="page-agv", domain_id=44)
    Mode.objects.create(name="page-mapping", nodes={"/lidar": {"state": "active"}}).robots.add(robot)
    page = operator_client.get("/robots/page-agv/modes/").content.decode()
    assert 'data-confirm="Apply mode page-mapping to page-agv?"' in page and "Import modes" not in page
    assert 'ws-connect="/ws/robots/page-agv/modes/"' in page
    viewer = viewer_client.get("/robots/page-agv/modes/").content.decode()
    assert "Apply page-mapping" not in viewer and "applying one needs the operator role" in viewer
    admin = client_of("ada-page", "admin")
    assert "Import modes" in admin.get("/robots/page-agv/modes/").content.decode()
    upload = SimpleUploadedFile("modes.yaml", SYSTEM_MODES_FILE.encode())
    preview = admin.post("/robots/page-agv/modes/import", {"file": upload}, HTTP_HX_REQUEST="true").content.decode()
    assert "platform-mapping" in preview and "right/wheel has no mode SLOW." in preview and "Save 3" not in preview


def test_readiness_predicates_are_checked_in_words():
    good = [{"node": "/lidar", "state": "active"}, {"node": "/lidar", "parameter": "rate", "equals": 8.0},
            {"node": "/lidar", "parameter": "rate", "min": 5}, {"topic": "/scan", "min_hz": 5, "window_s": 2}]
    assert definitions.readiness_problems(good) == []
    bad = [{"node": "/lidar", "state": "running"}, {"topic": "/scan", "min_hz": -1},
           {"topic": "/scan", "min_hz": 5, "window_s": 600}, {"node": "/lidar", "parameter": "rate", "min": "5"}]
    assert [p.split(" is not")[0] for p in definitions.readiness_problems(bad)] == [
        "Predicate 1", "Predicate 2", "Predicate 3", "Predicate 4"]


def test_a_mode_is_ready_only_while_every_predicate_holds_and_says_since_when_not(cell):
    part, robot, run = cell
    mode = Mode.objects.create(name="scanning", nodes={"/lidar": {"state": "active"}}, ready_when=[
        {"node": "/lidar", "state": "active"}, {"node": "/lidar", "parameter": "scan_rate_hz", "min": 5, "max": 20},
        {"topic": "/scan", "min_hz": 5, "window_s": 2}])
    mode.robots.add(robot)
    now_mode = CurrentMode.objects.create(robot=robot, mode=mode, since=timezone.now() - timedelta(seconds=30),
                                          run=run)
    # The gateway is asked to measure /scan; it reports it, and a rate no mode asks for is not kept.
    assert build_config("cell-m")["robots"][0]["rates"] == [{"topic": "/scan", "window_s": 2.0}]
    ManagedNode.objects.filter(robot=robot, name="/lidar").update(alive=True, state_label="active",
                                                                    state_id=sm.ACTIVE)
    apply_facts("cell-m", [part.fact(protocol.TOPIC_RATES, robot=robot.name, rates=[
        {"topic": "/scan", "hz": 2.5, "window_s": 2.0}, {"topic": "/other", "hz": 9.0, "window_s": 2.0}])])
    assert list(TopicRate.objects.values_list("topic", "hz")) == [("/scan", 2.5)]
    found = drift.summary(robot)
    assert not found["ready"] and found["not_ready_since"]
    assert [(c["words"], c["holds"], c["now"]) for c in found["readiness"]] == [
        ("/lidar active", True, "active"),
        ("/lidar scan_rate_hz within 5..20", False, "unknown"),
        ("/scan at >= 5 Hz over 2 s", False, "2.5 Hz")]
    rule = Rule.objects.get(name="Mode not ready")  # (alerts/installed_rules.py)
    assert conditions.current(rule, timezone.now())["modes-agv"].summary == (
        "Robot modes-agv is not ready in mode scanning: /lidar scan_rate_hz within 5..20 (now unknown); "
        "/scan at >= 5 Hz over 2 s (now 2.5 Hz).")
    lidar = ManagedNode.objects.get(robot=robot, name="/lidar")
    ParameterRecord.objects.create(node=lidar, robot_name=robot.name, node_name="/lidar", name="scan_rate_hz",
                                   new_value=8.0, outcome="succeeded", source="api", at=timezone.now())
    apply_facts("cell-m", [part.fact(protocol.TOPIC_RATES, robot=robot.name, rates=[
        {"topic": "/scan", "hz": 8.0, "window_s": 2.0}])])
    found = drift.summary(robot)
    assert found["ready"] and found["not_ready_since"] is None
    assert CurrentMode.objects.get(pk=now_mode.pk).not_ready_since is None
    refused = apply_facts("cell-m", [part.fact(protocol.TOPIC_RATES, robot=robot.name, rates=[
        {"topic": "/scan", "hz": "fast", "window_s": 2.0}])])
    assert refused.rejected == 1 and TopicRate.objects.get().hz == 8.0
