"""Robot modes on real nodes: defined through the API by an admin, applied back and forth by an
operator as one ordered run (down in reverse order, then up; parameters set before activation),
on record with who asked; a node that refuses its step; drift made by another tool shown."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from django.test import Client

from lifecycle_site.audit.models import ParameterRecord, TransitionRecord
from lifecycle_site.fleet.models import GroupRun, ManagedNode, Robot
from lifecycle_site.modes.models import CurrentMode
from tests import stack
from tests.conftest import client_of
from tests.integration.conftest import register, wait_node
from tests.integration.test_cli import cli

ROBOT = "it-modes"
DOMAIN_OFFSET = 41
ROS_CALL = Path(__file__).resolve().parent / "ros_call.py"

MAPPING = {
    "/lidar_driver": {"state": "active", "parameters": {"scan_rate_hz": 12.0}},
    "/camera_driver": {"state": "inactive"},
    "/planner": {"state": "unconfigured"},
}
PRODUCTION = {
    "/lidar_driver": {"state": "active", "parameters": {"scan_rate_hz": 6.0}},
    "/camera_driver": {"state": "active", "parameters": {"fps": 10.0}},
    "/planner": {"state": "active"},
    "/bad/flaky_node": {"state": None},
}


@pytest.fixture(scope="module")
def robot(gateway):
    register(ROBOT, stack.domain(DOMAIN_OFFSET))
    processes = [
        stack.start_robot("modes-main", stack.domain(DOMAIN_OFFSET), "lidar_driver,camera_driver,planner"),
        stack.start_robot("modes-bad", stack.domain(DOMAIN_OFFSET), "flaky_node",
                          "flaky_node.failure_mode:=fail_configure", namespace="/bad"),
    ]
    for name in ("lidar_driver", "camera_driver", "planner", "bad.flaky_node"):
        wait_node(None, f"{ROBOT}.{name}", alive=True, state="unconfigured")
    ManagedNode.objects.filter(robot__name=ROBOT, name="/lidar_driver").update(order=1)
    ManagedNode.objects.filter(robot__name=ROBOT, name="/camera_driver").update(order=2)
    ManagedNode.objects.filter(robot__name=ROBOT, name="/planner").update(order=3)
    yield processes
    for process in processes:
        process.stop()
    # Later modules find no robot of this one in a mode (its readiness would alert, its drift show).
    CurrentMode.objects.filter(robot__name=ROBOT).delete()
    Robot.objects.filter(name=ROBOT).update(enabled=False)


@pytest.fixture(scope="module")
def admin_api(live_db) -> Client:
    client = client_of("ada-admin", "admin")
    return client


def define(client: Client, name: str, nodes: dict):
    return client.put(f"/api/v1/modes/{name}", {"robots": [ROBOT], "nodes": nodes, "description": f"{name} mode"},
                      content_type="application/json")


def apply(client: Client, name: str, **body):
    return client.post(f"/api/v1/robots/{ROBOT}/modes/{name}/apply?wait=40", body, content_type="application/json")


def assert_states(**expected: str) -> None:
    found = dict(ManagedNode.objects.filter(robot__name=ROBOT).values_list("name", "state_label"))
    assert {name: found.get(f"/{name}") for name in expected} == expected


def parameter(api: Client, node: str, name: str):
    listing = api.get(f"/api/v1/nodes/{ROBOT}.{node}/parameters").json()["parameters"]
    return {p["name"]: p["value"] for p in listing}[name]


def test_only_an_admin_defines_a_mode_and_a_bad_definition_is_refused_in_words(api, admin_api, robot):
    assert define(api, "mapping", MAPPING).status_code == 403
    bad = define(admin_api, "mapping", {"/lidar_driver": {"state": "running"}, "lidar": {}})
    assert bad.status_code == 400
    message = bad.json()["error"]["message"]
    assert "'running' is not a state a mode can ask for" in message and "'lidar' is not a fully qualified" in message
    assert define(admin_api, "mapping", MAPPING).status_code == 201
    assert define(admin_api, "production", PRODUCTION).status_code == 201
    listed = api.get(f"/api/v1/robots/{ROBOT}/modes").json()
    assert [m["name"] for m in listed["modes"]] == ["mapping", "production"] and listed["mode"] is None


def test_modes_applied_back_and_forth_in_one_ordered_run_each_with_parameters_and_on_record(api, admin_api, robot):
    answer = apply(api, "mapping")
    assert answer.status_code == 200, answer.json()
    run = answer.json()["run"]
    assert (run["operation"], run["mode"], run["status"]) == ("mode", "mapping", "succeeded"), run
    assert_states(lidar_driver="active", camera_driver="inactive", planner="unconfigured")
    assert parameter(api, "lidar_driver", "scan_rate_hz") == 12.0
    lidar = next(r for r in run["results"] if r["node"] == "/lidar_driver")
    # Configured, its parameter set, then activated: the parameter before activation.
    assert [s["transition"] for s in lidar["steps"]] == ["configure", "set parameters", "activate"]
    record = ParameterRecord.objects.get(node__key=f"{ROBOT}.lidar_driver", name="scan_rate_hz", run_id=run["id"])
    assert (record.new_value, record.source, record.requested_by_name) == (12.0, "api", "ivan-operator")
    assert CurrentMode.objects.get(robot__name=ROBOT).mode.name == "mapping"
    # The mode's states are now the desired states (automatic recovery brings a node back to them).
    desired = dict(ManagedNode.objects.filter(robot__name=ROBOT).values_list("name", "desired_state"))
    assert (desired["/lidar_driver"], desired["/camera_driver"], desired["/planner"]) == (
        "active", "inactive", "unconfigured")

    answer = apply(api, "production", policy="continue")
    run = answer.json()["run"]
    assert run["status"] == "succeeded", run
    assert_states(lidar_driver="active", camera_driver="active", planner="active")
    assert parameter(api, "lidar_driver", "scan_rate_hz") == 6.0 and parameter(api, "camera_driver", "fps") == 10.0
    results = {r["node"]: r for r in run["results"]}
    # An active node's parameter is set where it is; the node the mode leaves alone is said to be.
    assert [s["transition"] for s in results["/lidar_driver"]["steps"]] == ["set parameters"]
    assert (results["/bad/flaky_node"]["outcome"], results["/bad/flaky_node"]["message"]) == (
        "skipped", "left alone (the mode does not say)")
    assert TransitionRecord.objects.filter(run_id=run["id"], transition_label="activate").count() == 2

    # Back to mapping: taken down in reverse order (planner before camera), in one run.
    run = apply(api, "mapping").json()["run"]
    assert run["status"] == "succeeded", run
    down = list(TransitionRecord.objects.filter(run_id=run["id"]).order_by("requested_at")
                .values_list("node_name", "transition_label"))
    assert down.index(("/planner", "deactivate")) < down.index(("/camera_driver", "deactivate"))
    assert api.get(f"/api/v1/robots/{ROBOT}/drift").json()["drift"] == []
    # Steps run by the gateway in the user's run, but only those of the run's mode carry the user's name.
    assert GroupRun.objects.get(pk=run["id"]).plan["mode"] == "mapping"


def test_a_node_that_refuses_its_step_fails_the_run_and_the_rest_goes_on_with_continue(api, admin_api, robot):
    define(admin_api, "with-bad", {"/bad/flaky_node": {"state": "active"}, "/planner": {"state": "inactive"}})
    run = apply(api, "with-bad", policy="continue").json()["run"]
    assert run["status"] == "partial", run
    results = {r["node"]: r for r in run["results"]}
    assert results["/bad/flaky_node"]["outcome"] == "failed" and "configure" in results["/bad/flaky_node"]["message"]
    assert results["/planner"]["outcome"] == "succeeded"
    drift = api.get(f"/api/v1/robots/{ROBOT}/drift").json()
    assert [(d["node"], d["kind"], d["want"], d["have"]) for d in drift["drift"]] == [
        ("/bad/flaky_node", "state", "active", "unconfigured")]


def test_drift_made_by_another_tool_is_shown_and_the_cli_says_it(api, admin_api, robot):
    run = apply(api, "mapping").json()["run"]
    assert run["status"] == "succeeded", run
    # Another tool (its own rclpy process) deactivates the lidar: 4 = deactivate.
    done = subprocess.run([sys.executable, str(ROS_CALL), str(stack.domain(DOMAIN_OFFSET)), "/lidar_driver", "4"],
                          capture_output=True, text=True, timeout=60, env=stack.environment())
    assert "success" in done.stdout, done.stdout + done.stderr
    found = stack.wait_for(lambda: api.get(f"/api/v1/robots/{ROBOT}/drift").json()["drift"], 10, "the drift")
    assert [(d["node"], d["kind"], d["want"], d["have"]) for d in found] == [
        ("/lidar_driver", "state", "active", "inactive")]
    assert found[0]["message"] == "/lidar_driver is inactive, the mode wants active"
    said = cli("mode", "drift", ROBOT)
    assert (said.code, said.out.strip()) == (1, "/lidar_driver is inactive, the mode wants active"), said.err
    assert cli("mode", "list", ROBOT).out.splitlines()[0].startswith("mapping (current since ")
    assert "/lidar_driver: active; scan_rate_hz=12.0" in cli("mode", "show", ROBOT, "mapping").out


def test_a_topic_rate_predicate_follows_a_real_publisher_whose_rate_changes(api, admin_api, robot):
    nodes = {"/lidar_driver": {"state": "active", "parameters": {"scan_rate_hz": 12.0}}}
    answer = admin_api.put("/api/v1/modes/scanning", {"robots": [ROBOT], "nodes": nodes, "ready_when": [
        {"topic": "/scan", "min_hz": 8, "window_s": 2}]}, content_type="application/json")
    assert answer.status_code == 201
    assert apply(api, "scanning").json()["run"]["status"] == "succeeded"

    def readiness():
        return api.get(f"/api/v1/robots/{ROBOT}/drift").json()

    ready = stack.wait_for(lambda: readiness()["ready"] or None, 20, "the mode ready (/scan at 12 Hz)")
    assert ready is True
    rate = float(readiness()["readiness"][0]["now"].split()[0])
    assert 9.0 <= rate <= 14.0, rate
    # The lidar slowed down by another tool: not ready once the window holds the slower rate.
    answer = api.patch(f"/api/v1/nodes/{ROBOT}.lidar_driver/parameters", {"scan_rate_hz": 4.0},
                       content_type="application/json")
    assert answer.status_code == 200, answer.json()
    found = stack.wait_for(lambda: None if readiness()["ready"] else readiness(), 20, "the mode not ready")
    assert found["not_ready_since"] and found["readiness"][0]["holds"] is False
    assert 2.0 <= float(found["readiness"][0]["now"].split()[0]) < 8.0
