"""Launch profiles on the real stack: the gateway runs a robot's process (the demo robot's nodes)
as its supervisor; restart, stop and start it through the API; a crash is respawned; each
action is on record with who asked; refusals answer clearly and are recorded too."""
from __future__ import annotations

import os
import signal
import sys
from pathlib import Path

import pytest
from django.test import Client
from django.utils import timezone

from lifecycle_site.audit.models import ProcessRecord, TransitionRecord
from lifecycle_site.fleet.models import ManagedNode, ProcessProfile, Robot
from lifecycle_site.gateway_link.gateway_client import GatewayError, call_gateway
from tests import stack
from tests.conftest import client_of, make_user
from tests.integration.conftest import register, wait_node
from tests.integration.test_cli import cli

ROBOT = "proc-agv"
PROCESS = "drivers"
NODE = f"{ROBOT}.lidar_driver"
ROOT = Path(__file__).resolve().parents[2]


def profile() -> ProcessProfile:
    return ProcessProfile.objects.select_related("robot").get(robot__name=ROBOT, name=PROCESS)


def running_pid() -> int:
    """The pid the gateway reports once the process runs (its status on the profile)."""
    found = stack.wait_for(lambda: (p := profile()).status == "running" and p.pid, 30, "the process to run")
    return int(found)


@pytest.fixture(scope="module")
def supervised(gateway):
    robot = register(ROBOT, stack.domain(35))
    Robot.objects.filter(pk=robot.pk).update(auto_recover=True)
    # Through a shell, as a launch file starts its nodes: the node's process is a child of the supervised one.
    nodes = f"{sys.executable} -m ros_gateway.demo.robot --domain {stack.domain(35)} --nodes lidar_driver"
    made = ProcessProfile.objects.create(
        robot=robot, name=PROCESS, command="/bin/sh", args=["-c", f"{nodes}; exit $?"], cwd=str(ROOT),
        respawn_delay_s=0.2, stop_grace_s=5.0, env={"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"},
        secret_env={"DEMO_TOKEN": "not-shown"})
    Robot.objects.get(pk=robot.pk).save()  # (saving the robot publishes its gateway's config again)
    pid = running_pid()
    wait_node(None, NODE, timeout=40, alive=True)
    yield made
    ProcessProfile.objects.filter(pk=made.pk).delete()
    Robot.objects.get(pk=robot.pk).save()
    stack.wait_for(lambda: not stack.pid_alive(pid) and not stack.pid_alive(profile_pid_or(pid)), 30,
                   "the gateway to stop the process")


def profile_pid_or(pid: int) -> int:
    found = ProcessProfile.objects.filter(robot__name=ROBOT, name=PROCESS).values_list("pid", flat=True).first()
    return found or pid


def control(api: Client, action: str, process: str = PROCESS):
    return api.post(f"/api/v1/robots/{ROBOT}/processes/{process}", {"action": action},
                    content_type="application/json")


def test_the_processes_are_listed_with_their_status_and_never_a_secret(api, supervised):
    listing = api.get(f"/api/v1/robots/{ROBOT}/processes")
    assert listing.status_code == 200
    (shown,) = listing.json()["processes"]
    assert shown["name"] == PROCESS and shown["status"] == "running" and shown["pid"] == running_pid()
    assert "ros_gateway.demo.robot" in shown["command"]
    # The gateway tells which process runs the node (for the node page's "restart process").
    stack.wait_for(lambda: ManagedNode.objects.filter(key=NODE, supervised_by=PROCESS).exists(), 20,
                   "the node attributed to its launch profile")
    assert "not-shown" not in listing.content.decode() and "DEMO_TOKEN" not in listing.content.decode()


def test_a_restart_gets_a_new_process_whose_node_is_driven_back_to_its_desired_state(api, supervised):
    activated = api.post(f"/api/v1/nodes/{NODE}/transition", {"transition": "configure"},
                         content_type="application/json")
    assert activated.status_code in (200, 409), activated.json()
    ManagedNode.objects.filter(key=NODE).update(desired_state="inactive")
    Robot.objects.get(name=ROBOT).save()  # the gateway learns the desired state
    wait_node(None, NODE, state="inactive")
    before = running_pid()
    asked = timezone.now()  # (the new instance may be seen before the restart's record is made)
    answer = control(api, "restart")
    assert answer.status_code == 200, answer.json()
    record = answer.json()["record"]
    assert (record["action"], record["outcome"], record["source"], record["requested_by"]) == (
        "restart", "succeeded", "api", "ivan-operator")
    assert record["old_pid"] == before and record["pid"] not in (None, before)
    assert not stack.pid_alive(before)
    assert answer.json()["process"]["restarts"] >= 1
    # The new instance comes up unconfigured; recovery brings it back to its desired state.
    stack.wait_for(lambda: TransitionRecord.objects.filter(node__key=NODE, outcome="process_restarted",
                                                           completed_at__gte=asked).exists(), 40, "the new instance")
    recovered = stack.wait_for(lambda: TransitionRecord.objects.filter(
        node__key=NODE, source="recovery", transition_label="configure", outcome="succeeded",
        requested_at__gte=asked).first(), 40, "the recovery's configure")
    assert recovered.result_state_label == "inactive"
    wait_node(None, NODE, alive=True, state="inactive")


def test_a_crash_is_respawned_and_both_are_on_record(supervised):
    before = running_pid()
    os.kill(before, signal.SIGKILL)
    exited = stack.wait_for(lambda: ProcessRecord.objects.filter(process_name=PROCESS, action="exited",
                                                                 old_pid=before).first(), 20, "the exit's record")
    assert (exited.source, exited.exit_signal, exited.requested_by_name) == ("supervisor", "SIGKILL", "")
    respawned = stack.wait_for(lambda: ProcessRecord.objects.filter(process_name=PROCESS, action="respawn",
                                                                    at__gte=exited.at).first(), 20, "the respawn")
    assert respawned.outcome == "succeeded" and respawned.pid != before
    assert running_pid() == respawned.pid
    wait_node(None, NODE, timeout=40, alive=True)


def test_stop_then_start(api, supervised):
    before = running_pid()
    stopped = control(api, "stop")
    assert stopped.status_code == 200, stopped.json()
    assert stopped.json()["process"]["status"] == "stopped" and not stack.pid_alive(before)
    again = control(api, "stop")
    assert again.status_code == 409 and again.json()["error"]["code"] == "process_state"
    assert ProcessRecord.objects.get(pk=again.json()["error"]["record_id"]).outcome == "rejected"
    wait_node(None, NODE, timeout=40, alive=False)
    started = control(api, "start")
    assert started.status_code == 200, started.json()
    assert started.json()["record"]["pid"] == running_pid()
    wait_node(None, NODE, timeout=40, alive=True)


def test_what_cannot_be_done_is_refused_plainly(api, supervised):
    unknown = control(api, "restart", "no-such-process")
    assert unknown.status_code == 404 and unknown.json()["error"]["code"] == "unknown_process"
    assert "Robot proc-agv has no process 'no-such-process' (its processes: drivers" in \
        unknown.json()["error"]["message"]
    action = control(api, "reboot")
    assert action.status_code == 400 and action.json()["error"]["code"] == "unknown_action"
    viewer = client_of("vera-processes", "viewer")
    assert control(viewer, "restart").status_code == 403
    # The gateway itself acts only on its own profiles, whatever it is sent.
    with pytest.raises(GatewayError) as refused:
        call_gateway("local", "process_control", robot=ROBOT, process="sshd", action="stop", source="api")
    assert refused.value.code == "unknown_process"
    with pytest.raises(GatewayError) as refused:
        call_gateway("local", "process_control", robot="not-a-watched-robot", process=PROCESS, action="stop",
                     source="api")
    assert refused.value.code == "robot_not_watched"


def test_the_command_line_lists_and_restarts_a_process(supervised):
    make_user("carl-cli", "operator")
    listed = cli("process", ROBOT)
    assert listed.code == 0 and listed.out.startswith(f"{PROCESS}: running, pid {running_pid()}"), listed
    before = running_pid()
    restarted = cli("process", ROBOT, PROCESS, "restart", "--user", "carl-cli")
    assert restarted.code == 0, restarted
    assert "restarted as pid" in restarted.out and str(before) in restarted.out
    record = ProcessRecord.objects.filter(action="restart", source="cli").latest("at")
    assert (record.requested_by_name, record.old_pid) == ("carl-cli", before)
    unknown = cli("process", ROBOT, "nope", "stop", "--user", "carl-cli")
    assert unknown.code == 2 and "Robot proc-agv has no process 'nope'" in unknown.err
    missing = cli("process", ROBOT, PROCESS, "--user", "carl-cli")
    assert missing.code == 2 and "Give an action: start, stop, restart." in missing.err
    wait_node(None, NODE, timeout=40, alive=True)


HUNG = "hung-agv"


@pytest.fixture
def hanging(gateway):
    """A robot whose flaky node hangs in on_configure (failure_mode=hang), run by a launch profile
    that gives its stop signal 1 s."""
    robot = register(HUNG, stack.domain(36))
    made = ProcessProfile.objects.create(
        robot=robot, name="flaky", command=sys.executable, cwd=str(ROOT), stop_grace_s=1.0,
        args=["-m", "ros_gateway.demo.robot", "--domain", str(stack.domain(36)), "--nodes", "flaky_node",
              "--param", "flaky_node.failure_mode:=hang"], env={"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"})
    Robot.objects.get(pk=robot.pk).save()
    wait_node(None, f"{HUNG}.flaky_node", timeout=40, alive=True, state="unconfigured")
    yield made
    pid = ProcessProfile.objects.filter(pk=made.pk).values_list("pid", flat=True).first()
    made.delete()
    Robot.objects.get(pk=robot.pk).save()
    if pid:
        stack.wait_for(lambda: not stack.pid_alive(pid), 30, "the gateway to stop the hung process")


def test_a_hung_process_is_restarted_with_sigkill_after_its_grace(api, hanging):
    key = f"{HUNG}.flaky_node"
    stuck = api.post(f"/api/v1/nodes/{key}/transition", {"transition": "configure", "timeout": 1},
                     content_type="application/json")
    assert stuck.status_code == 504 and stuck.json()["error"]["code"] == "timeout", stuck.json()
    before = ProcessProfile.objects.get(pk=hanging.pk).pid
    asked = timezone.now()  # (the new instance may be seen before the restart's record is made)
    answer = api.post(f"/api/v1/robots/{HUNG}/processes/flaky", {"action": "restart"},
                      content_type="application/json")
    assert answer.status_code == 200, answer.json()
    record = answer.json()["record"]
    assert record["old_pid"] == before and record["pid"] != before
    assert "SIGINT, then SIGKILL after 1.0 s without ending" in record["message"]
    assert not stack.pid_alive(before)
    stack.wait_for(lambda: TransitionRecord.objects.filter(node__key=key, outcome="process_restarted",
                                                           completed_at__gte=asked).exists(), 40, "the new instance")
    wait_node(None, key, alive=True, state="unconfigured")



def test_the_page_shows_each_running_process_cpu_and_memory_as_its_gateway_measures_them(supervised, gateway):

    client = client_of("ivan-viewer", "viewer")
    profile_id = profile().pk
    answer = client.get(f"/robots/{ROBOT}/processes/usage")  # the first ask measures over 0.3 s
    assert answer.status_code == 200, answer.status_code
    text = answer.content.decode()
    cell = text.split(f'id="usage-{profile_id}"')[1].split("</span>")[0]
    assert 'hx-swap-oob="true"' in cell and " MB" in cell and " %" in cell, cell
    megabytes = float(cell.split("·")[1].split("MB")[0])
    assert 10 < megabytes < 2000  # a shell and a Python process with rclpy
    assert "(2 processes)" in text  # the shell and its child, one process group



def test_a_finalized_node_comes_back_by_restarting_its_process(api, supervised):
    """After shutdown only a new process brings a node back: its page offers the restart, and the
    new instance is driven to its desired state."""
    ManagedNode.objects.filter(key=NODE).update(desired_state="inactive")
    Robot.objects.get(name=ROBOT).save()  # the gateway learns the desired state
    wait_node(None, NODE, alive=True)
    for transition in ("configure", "shutdown"):
        api.post(f"/api/v1/nodes/{NODE}/transition", {"transition": transition}, content_type="application/json")
    wait_node(None, NODE, alive=True, state="finalized")
    page = api.get(f"/nodes/{NODE}/").content.decode()
    assert f"Restart process {PROCESS}" in page
    asked = timezone.now()
    answer = api.post(f"/robots/{ROBOT}/processes/{PROCESS}/restart", {"from": "node"})  # the node page's button
    assert answer.status_code == 200 and "restarted as pid" in answer.content.decode()
    stack.wait_for(lambda: TransitionRecord.objects.filter(node__key=NODE, outcome="process_restarted",
                                                           completed_at__gte=asked).exists(), 40, "the new instance")
    wait_node(None, NODE, timeout=40, alive=True, state="inactive")


def test_what_a_killed_gateway_left_running_is_ended_by_its_next_instance(supervised, gateway, request):
    """(Last in this module: it kills the module's gateway.) The profile runs its nodes through a
    shell: the kernel ends the shell with the gateway (PR_SET_PDEATHSIG), not the shell's child.
    The gateway's next instance ends that orphan (it carries the gateway's mark in its
    environment) before it starts the profile again."""
    shell = running_pid()
    (orphan,) = (int(pid) for pid in Path(f"/proc/{shell}/task/{shell}/children").read_text().split())
    killed_at = timezone.now()
    gateway.kill()
    stack.wait_for(lambda: not stack.pid_alive(shell), 10, "the shell to end with its gateway")
    assert stack.pid_alive(orphan), "the shell's child outlives a killed gateway (what this test is about)"
    successor = stack.start_gateway()
    request.addfinalizer(successor.stop)
    stack.wait_for(lambda: not stack.pid_alive(orphan), 20, "the orphan ended by the gateway's next instance")
    ended = stack.wait_for(lambda: ProcessRecord.objects.filter(
        process_name=PROCESS, action="stop", source="supervisor", at__gte=killed_at).first(), 30, "its record")
    assert ended.old_pid == orphan and "left running by the gateway's previous instance" in ended.message
    started = stack.wait_for(lambda: ProcessRecord.objects.filter(
        process_name=PROCESS, action="start", outcome="succeeded", at__gte=killed_at).first(), 30, "the new start")
    assert started.pid not in (shell, orphan) and running_pid() == started.pid
    assert started.at >= ended.at  # ended first, then started: never two instances side by side
    wait_node(None, NODE, timeout=40, alive=True)
