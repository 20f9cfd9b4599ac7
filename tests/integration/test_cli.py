"""``manage.py lifecycle`` (ros2 lifecycle's verbs, against the site) with the real gateway and
real rclpy nodes: in-process through call_command, and as a real subprocess."""
from __future__ import annotations

import io
import json
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from datetime import timedelta

import pytest
from django.conf import settings
from django.core.management import CommandError, call_command
from django.test import override_settings
from django.utils import timezone

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import GroupRun, ManagedNode, Robot
from tests import stack
from tests.conftest import make_user
from tests.integration.conftest import register, wait_node

ROBOT_A, ROBOT_B, ROBOT_SLOW, ROBOT_RUNS = "cli-a", "cli-b", "cli-slow", "cli-runs"
OPERATOR, VIEWER = "cli-operator", "cli-viewer"
UNCONFIGURED_LIST = ["- configure [1]", "\tStart: unconfigured", "\tGoal: configuring",
                     "- shutdown [5]", "\tStart: unconfigured", "\tGoal: shuttingdown"]


@dataclass
class Result:
    code: int
    out: str
    err: str

    @property
    def lines(self) -> list[str]:
        return self.out.splitlines()


def cli(*args: str) -> Result:
    """Run ``manage.py lifecycle ARGS`` in this process; CommandError carries the exit status."""
    stdout, stderr = io.StringIO(), io.StringIO()
    try:
        call_command("lifecycle", *args, stdout=stdout, stderr=stderr)
        code = 0
    except CommandError as exc:
        code = exc.returncode
        if not stderr.getvalue():  # an argparse error: the command itself never ran
            stderr.write(str(exc))
    return Result(code, stdout.getvalue(), stderr.getvalue())


def cli_process(*args: str, timeout: float = 60, **env: str) -> tuple[Result, float]:
    """Run it as a real process, as an operator would; also returns the wall time in seconds."""
    began = time.perf_counter()
    done = subprocess.run([sys.executable, "manage.py", "lifecycle", *args], cwd=stack.ROOT,
                          env=stack.environment(**env), capture_output=True, text=True, timeout=timeout)
    return Result(done.returncode, done.stdout, done.stderr), time.perf_counter() - began


def latest_record(key: str) -> TransitionRecord:
    return TransitionRecord.objects.filter(node__key=key).order_by("-id").first()


@pytest.fixture(scope="module")
def robots(gateway):
    make_user(OPERATOR, "operator")
    make_user(VIEWER, "viewer")
    register(ROBOT_A, stack.domain(20))
    register(ROBOT_B, stack.domain(21), namespace="/b")
    register(ROBOT_SLOW, stack.domain(21), namespace="/slow")
    register(ROBOT_RUNS, stack.domain(22))
    processes = [
        stack.start_robot("cli-a-nodes", stack.domain(20), "joy_to_vel,lidar_driver,camera_driver",
                          extra=("--generic", "1")),
        stack.start_robot("cli-b-nodes", stack.domain(21), "joy_to_vel,flaky_node",
                          "flaky_node.failure_mode:=fail_configure", namespace="/b"),
        stack.start_robot("cli-slow-nodes", stack.domain(21), "flaky_node", "flaky_node.failure_mode:=slow_configure",
                          "flaky_node.slow_seconds:=5.0", namespace="/slow"),
        stack.start_robot("cli-runs-nodes", stack.domain(22), "lidar_driver,camera_driver,flaky_node",
                          "flaky_node.failure_mode:=fail_configure"),
    ]
    for key in ("cli-a.joy_to_vel", "cli-a.lidar_driver", "cli-a.camera_driver", "cli-a.generic_000",
                "cli-b.b.joy_to_vel", "cli-b.b.flaky_node", "cli-slow.slow.flaky_node", "cli-runs.lidar_driver",
                "cli-runs.camera_driver", "cli-runs.flaky_node"):
        wait_node(None, key, alive=True, state="unconfigured", timeout=30)
    # A node the site knew but that is gone now (its process ended long ago).
    ManagedNode.objects.update_or_create(
        robot=Robot.objects.get(name=ROBOT_A), name="/gone_node",
        defaults={"alive": False, "state_id": 3, "state_label": "active",
                  "last_seen": timezone.now() - timedelta(hours=1)},
    )
    yield processes
    for process in processes:
        process.stop()


def test_nodes_prints_ros_names_with_robot_and_robot_prefixed_lines_without(robots, api):
    result = cli("nodes", "--robot", ROBOT_A)
    assert result.code == 0 and result.err == ""
    assert result.lines == ["/camera_driver", "/generic_000", "/joy_to_vel", "/lidar_driver"]
    everything = cli("nodes").lines
    assert {f"{ROBOT_A} /joy_to_vel", f"{ROBOT_B} /b/joy_to_vel", f"{ROBOT_SLOW} /slow/flaky_node"} <= set(everything)
    assert not any("gone_node" in line for line in everything), "lost nodes are left out without -a"
    assert f"{ROBOT_A} /gone_node (lost)" in cli("nodes", "-a").lines
    assert cli("nodes", "--robot", ROBOT_A, "-a", "-c").lines == ["5"]
    listed = json.loads(cli("nodes", "--robot", ROBOT_A, "--json").out)
    from_api = api.get(f"/api/v1/nodes?robot={ROBOT_A}").json()
    assert set(listed) == {"nodes"} and len(listed["nodes"]) == 4
    node = next(n for n in listed["nodes"] if n["name"] == "/lidar_driver")
    assert set(node) == set(from_api["nodes"][0])
    assert node["id"] == f"{ROBOT_A}.lidar_driver" and node["state"] == {"id": 1, "label": "unconfigured"}


def test_get_prints_the_state_as_ros2_does(robots):
    assert cli("get", f"{ROBOT_A}.joy_to_vel").out == "unconfigured [1]\n"
    assert cli("get", "--robot", ROBOT_A, "/joy_to_vel").out == "unconfigured [1]\n"
    assert cli("get", "--robot", ROBOT_B, "joy_to_vel").out == "unconfigured [1]\n", "relative to the namespace"
    per_robot = cli("get", "--robot", ROBOT_A)
    assert per_robot.code == 0 and "/joy_to_vel: unconfigured [1]" in per_robot.lines
    assert len(per_robot.lines) == 4
    everything = cli("get").lines
    assert f"{ROBOT_A} /joy_to_vel: unconfigured [1]" in everything
    assert f"{ROBOT_B} /b/joy_to_vel: unconfigured [1]" in everything
    assert "/gone_node: active [3] (lost)" in cli("get", "--robot", ROBOT_A, "-a").lines
    assert f"{ROBOT_A} /gone_node: active [3] (lost)" in cli("get", "-a").lines
    body = json.loads(cli("get", f"{ROBOT_A}.joy_to_vel", "--json").out)
    assert body["state"] == {"id": 1, "label": "unconfigured"} and body["live"] is True
    assert body["id"] == f"{ROBOT_A}.joy_to_vel" and body["transitions"][0] == {"id": 1, "label": "configure"}
    result = cli("get", f"{ROBOT_A}.gone_node")  # a lost node: its last known state, and a note
    assert result.code == 0 and result.out == "active [3]\n"
    assert "is not running" in result.err and "last known state" in result.err


def test_set_success_by_label_and_by_id_is_audited_as_cli(robots):
    key = f"{ROBOT_A}.lidar_driver"
    result = cli("set", key, "configure", "--user", OPERATOR)
    assert (result.code, result.out, result.err) == (0, "Transitioning successful\n", "")
    assert cli("get", key).out == "inactive [2]\n"
    record = latest_record(key)
    assert (record.transition_label, record.outcome, record.source, record.requested_by_name) == (
        "configure", "succeeded", "cli", OPERATOR)
    result = cli("set", "--robot", ROBOT_A, "lidar_driver", "3", "--user", OPERATOR, "--timeout", "5")
    assert result.code == 0 and result.out == "Transitioning successful\n"
    assert cli("get", key).out == "active [3]\n"
    assert latest_record(key).transition_label == "activate" and latest_record(key).source == "cli"


def test_set_failure_prints_transitioning_failed_with_the_reason_and_exits_1(robots):
    key = f"{ROBOT_B}.b.flaky_node"
    result = cli("set", "--robot", ROBOT_B, "/b/flaky_node", "configure", "--user", OPERATOR)
    assert result.code == 1 and result.out == "Transitioning failed\n"
    assert "FAILURE" in result.err and "simulated hardware not found" in result.err
    record = latest_record(key)
    assert (record.outcome, record.source, record.requested_by_name) == ("failed", "cli", OPERATOR)
    body = json.loads(cli("set", key, "configure", "--user", OPERATOR, "--json").out)
    assert body["error"]["code"] == "transition_failed" and body["error"]["state"]["label"] == "unconfigured"


def test_invalid_and_unknown_transitions(robots):
    key = f"{ROBOT_A}.camera_driver"
    result = cli("set", key, "activate", "--user", OPERATOR)
    assert result.code == 1 and result.out == "Transitioning failed\n"
    assert "not possible from state unconfigured" in result.err
    assert "- configure [1]\n- shutdown [5]" in result.err
    assert (latest_record(key).outcome, latest_record(key).source) == ("rejected", "cli")
    body = json.loads(cli("set", key, "activate", "--user", OPERATOR, "--json").out)
    assert body["error"]["code"] == "invalid_transition"
    assert [t["label"] for t in body["error"]["valid_transitions"]] == ["configure", "shutdown"]
    unknown = cli("set", key, "jump", "--user", OPERATOR)
    assert unknown.code == 2 and "'jump' is not a lifecycle transition" in unknown.err and unknown.out == ""


def test_list_and_list_all_have_the_ros2_shape(robots):
    key = f"{ROBOT_A}.camera_driver"
    assert cli("list", key).lines == UNCONFIGURED_LIST
    graph = cli("list", "--robot", ROBOT_A, "camera_driver", "-a").lines
    assert len(graph) % 3 == 0 and len(graph) // 3 >= 20, graph
    blocks = [graph[i:i + 3] for i in range(0, len(graph), 3)]
    # The node's own labels, as ros2 shows them (rclpy calls the internal ones transition_success ...).
    assert ["- transition_success [10]", "\tStart: configuring", "\tGoal: inactive"] in blocks
    assert ["- deactivate [4]", "\tStart: active", "\tGoal: deactivating"] in blocks
    assert all(b[0].startswith("- ") and b[1].startswith("\tStart: ") and b[2].startswith("\tGoal: ") for b in blocks)
    body = json.loads(cli("list", key, "--json").out)
    assert body["node"] == key and [t["label"] for t in body["transitions"]] == ["configure", "shutdown"]
    assert body["transitions"][0]["goal"] == {"id": 10, "label": "configuring"}
    assert len(json.loads(cli("list", key, "-a", "--json").out)["transition_graph"]) == len(blocks)


def test_unknown_node_or_robot_exits_2_and_names_the_known_ones(robots):
    result = cli("get", "no-such.node")
    assert result.code == 2 and result.out == ""
    assert "There is no node 'no-such.node'" in result.err and f"{ROBOT_A}.camera_driver" in result.err
    if ManagedNode.objects.count() > 10:
        assert "more (" in result.err, "at most ten are listed"
    ros_name = cli("set", "/joy_to_vel", "configure", "--user", OPERATOR)
    assert ros_name.code == 2 and "needs --robot" in ros_name.err and f"{ROBOT_A}.joy_to_vel" in ros_name.err
    dotted = cli("get", f"{ROBOT_A}.nope")
    assert dotted.code == 2 and f"Robot {ROBOT_A} has no node '{ROBOT_A}.nope'" in dotted.err
    assert "/lidar_driver" in dotted.err
    on_robot = cli("list", "--robot", ROBOT_A, "nope")
    assert on_robot.code == 2 and f"Robot {ROBOT_A} has no node 'nope'. Its nodes: /camera_driver" in on_robot.err
    robot = cli("nodes", "--robot", "no-such-robot", "--json")
    assert robot.code == 2 and "There is no robot 'no-such-robot'" in robot.err and ROBOT_A in robot.err
    assert json.loads(robot.out)["error"]["code"] == "not_found"
    assert cli("bringup", "no-such-robot", "--user", OPERATOR).code == 2


def test_changes_need_a_site_user_allowed_to_operate(robots, monkeypatch):
    key = f"{ROBOT_A}.joy_to_vel"
    monkeypatch.delenv("LIFECYCLE_USER", raising=False)
    monkeypatch.setattr("getpass.getuser", lambda: "no-such-login")
    refused = cli("set", key, "configure")
    assert refused.code == 2 and "No site user" in refused.err and "no-such-login" in refused.err
    assert cli("get", key).code == 0, "read-only verbs need no user"
    assert "There is no site user 'ghost'" in cli("set", key, "configure", "--user", "ghost").err
    viewer = cli("set", key, "configure", "--user", VIEWER)
    assert viewer.code == 2 and "may not operate nodes" in viewer.err
    assert cli("get", key).out == "unconfigured [1]\n", "nothing was sent"
    monkeypatch.setenv("LIFECYCLE_USER", OPERATOR)
    assert cli("set", key, "configure").code == 0
    assert latest_record(key).requested_by_name == OPERATOR
    assert cli("set", key, "cleanup").code == 0


def test_gateway_offline_is_one_line_and_exit_3_and_get_falls_back(robots):
    key = f"{ROBOT_A}.joy_to_vel"
    stale = {**settings.LIFECYCLE, "GATEWAY_OFFLINE_AFTER": -3600}  # every heartbeat looks too old
    with override_settings(LIFECYCLE=stale):
        changed = cli("set", key, "configure", "--user", OPERATOR)
        listed = cli("list", key)
        got = cli("get", key)
    assert changed.code == 3 and changed.out == "" and "Gateway local is offline" in changed.err
    assert len(changed.err.strip().splitlines()) == 1
    assert listed.code == 3 and "Gateway local is offline" in listed.err
    assert got.code == 0 and got.out == "unconfigured [1]\n" and "last known state" in got.err


def test_as_a_real_process_get_is_fast_and_errors_have_no_traceback(robots, capsys):
    key = f"{ROBOT_A}.joy_to_vel"
    result, wall = cli_process("get", key)
    assert (result.code, result.out, result.err) == (0, "unconfigured [1]\n", ""), result
    began = time.perf_counter()
    assert cli("get", key).code == 0
    in_process = time.perf_counter() - began
    with capsys.disabled():
        print(f"\n[cli timing] 'manage.py lifecycle get' as a process: {wall * 1000:.0f} ms "
              f"(Python + Django start-up included); the same get in-process: {in_process * 1000:.1f} ms")
    unknown, _ = cli_process("get", "no-such.node")
    assert unknown.code == 2 and unknown.out == "" and "Traceback" not in unknown.err
    assert unknown.err.startswith("There is no node") and "CommandError" not in unknown.err
    usage, _ = cli_process("set", key)
    assert usage.code == 2 and "TRANSITION" in usage.err and "Traceback" not in usage.err


def test_redis_down_is_exit_3_without_traceback(robots):
    key = f"{ROBOT_A}.joy_to_vel"
    nowhere = "redis://127.0.0.1:9/0"  # the discard port: nothing listens there
    changed, _ = cli_process("set", key, "configure", "--user", OPERATOR, REDIS_URL=nowhere)
    assert changed.code == 3 and changed.out == "" and "Traceback" not in changed.err
    assert "Redis" in changed.err and len(changed.err.strip().splitlines()) == 1
    got, _ = cli_process("get", key, REDIS_URL=nowhere)
    assert got.code == 0 and got.out == "unconfigured [1]\n" and "last known state" in got.err


def test_ctrl_c_ends_quietly(robots):
    key = f"{ROBOT_SLOW}.slow.flaky_node"
    slow_node = robots[2]
    begun = slow_node.output().count("configuring slowly")
    process = subprocess.Popen(
        [sys.executable, "manage.py", "lifecycle", "set", key, "configure", "--timeout", "20", "--user", OPERATOR],
        cwd=stack.ROOT, env=stack.environment(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        # While the node configures (5 s): told by the node itself, not by the stored state, which
        # a busy ingest may store only after the command has ended.
        stack.wait_for(lambda: slow_node.output().count("configuring slowly") > begun, 20, "the slow configure")
        process.send_signal(signal.SIGINT)
        out, err = process.communicate(timeout=20)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 130 and "Traceback" not in err and err.strip() == "Interrupted.", err
    wait_node(None, key, state="inactive", timeout=20)  # the transition itself went on in the gateway


def test_bringup_and_shutdown_print_one_line_per_node_and_a_summary(robots):
    ok = cli("bringup", ROBOT_RUNS, "--user", OPERATOR, "--policy", "continue", "--timeout", "5", "--wait", "60")
    lines = ok.lines
    assert ok.code == 1, "the failing flaky_node makes the run partial"
    # No positions set: the three go side by side and are printed as they finish.
    lines = sorted(ok.lines[:3]) + ok.lines[3:]
    assert lines[0].startswith("/camera_driver: configure ok, activate ok (") and lines[0].endswith(" ms)")
    assert lines[1].startswith("/flaky_node: configure FAILED: ") and "simulated hardware not found" in lines[1]
    assert lines[2].startswith("/lidar_driver: configure ok, activate ok (")
    assert lines[3].startswith(f"bringup {ROBOT_RUNS}: partly failed (2 succeeded, 1 failed) in ")
    run = GroupRun.objects.filter(robot__name=ROBOT_RUNS).first()
    records = TransitionRecord.objects.filter(run_id=run.id)
    assert records.count() == 5 and {(r.source, r.requested_by_name) for r in records} == {("cli", OPERATOR)}

    # flaky_node first in the order: with the default policy its failure stops the run.
    ManagedNode.objects.filter(robot__name=ROBOT_RUNS, name="/flaky_node").update(order=1)
    again = cli("bringup", "--robot", ROBOT_RUNS, "--user", OPERATOR, "--wait", "60")
    ManagedNode.objects.filter(robot__name=ROBOT_RUNS).update(order=None)
    assert again.code == 1 and again.lines[0].startswith("/flaky_node: configure FAILED: ")
    assert sorted(again.lines[1:3]) == [
        "/camera_driver: not run (the run stopped after /flaky_node failed)",
        "/lidar_driver: not run (the run stopped after /flaky_node failed)"]

    restart = cli("restart", "--robot", ROBOT_RUNS, "camera_driver", "--user", OPERATOR, "--wait", "60")
    assert restart.code == 0, restart
    assert restart.lines[0].startswith("/camera_driver: deactivate ok, cleanup ok, configure ok, activate ok (")
    assert restart.lines[1].startswith(f"restart {ROBOT_RUNS}: succeeded")

    paused = cli("pause", ROBOT_RUNS, "--user", OPERATOR, "--json")
    assert paused.code == 0, paused
    run = json.loads(paused.out)["run"]
    assert run["status"] == "succeeded" and run["source"] == "cli" and run["requested_by"] == OPERATOR
    assert {r["node"]: r["outcome"] for r in run["results"]} == {
        "/lidar_driver": "succeeded", "/flaky_node": "skipped", "/camera_driver": "succeeded"}

    down = cli("shutdown", ROBOT_RUNS, "--user", OPERATOR, "--wait", "60")
    assert down.code == 0, down
    assert sorted(line.split(":")[0] for line in down.lines[:3]) == ["/camera_driver", "/flaky_node", "/lidar_driver"]
    assert all(": shutdown ok (" in line for line in down.lines[:3]), down.lines
    assert down.lines[3].startswith(f"shutdown {ROBOT_RUNS}: succeeded (3 succeeded)")
    assert cli("get", "--robot", ROBOT_RUNS).lines == [
        "/camera_driver: finalized [4]", "/flaky_node: finalized [4]", "/lidar_driver: finalized [4]"]
