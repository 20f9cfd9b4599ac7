"""The gateway as a robot's systemd supervisor, with a real systemd: a container of the product's
image with systemd as PID 1 (tests/deploy/systemd/) is the robot's host, its gateway and its
nodes two units of it, as a robot installed with systemd runs them. The gateway finds the node's
process in the unit demo-node.service (its cgroup) and names it "systemd:demo-node.service";
restart, stop and start from the API go through systemctl; the record has the old process's end,
and the node's new instance is driven back to its desired state (active)."""
from __future__ import annotations

import os
import shlex
from pathlib import Path

import pytest
from django.test import Client
from django.utils import timezone

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import Gateway, ManagedNode, Robot
from lifecycle_site.gateway_link import gateways
from tests import stack
from tests.deploy import engine
from tests.deploy.test_host_units import activate_as_desired

ROBOT, GATEWAY, UNIT = "sd-agv", "robot-sd", "demo-node.service"
NODE, PROCESS = f"{ROBOT}.lidar_driver", f"systemd:{UNIT}"
HERE = Path(__file__).resolve().parent / "systemd"


def systemd_flags() -> list[str]:
    """What systemd needs to boot in a container on this host (no --privileged on v1/hybrid hosts)."""
    if Path("/sys/fs/cgroup/systemd/cgroup.procs").exists():  # v1 or hybrid: its own hierarchy, writable
        return ["-v", "/sys/fs/cgroup/systemd:/sys/fs/cgroup/systemd:rw", "--tmpfs", "/run", "--tmpfs", "/run/lock"]
    return ["--privileged", "--cgroupns", "private", "--tmpfs", "/run", "--tmpfs", "/run/lock"]  # v2 only


def env_file(path: Path, values: dict[str, str]) -> Path:
    path.write_text("".join(f"{key}={shlex.quote(value)}\n" for key, value in values.items()))
    return path


@pytest.fixture(scope="module")
def robot_host(image, docker_engine, scratch, redis_server, live_db, ingest):
    """The systemd container: its gateway on this run's Redis, its robot in this run's domain."""
    tag = "lifecycle-systemd-test:latest"
    engine.run(["docker", "build", "-q", "--build-arg", f"BASE={image}", "-t", tag, str(HERE)], timeout=600)
    ours = stack.environment()
    gateway_env = {key: value for key, value in ours.items() if key.startswith("LIFECYCLE_") or key == "REDIS_URL"}
    gateway_env["DATABASE_URL"] = stack.GATEWAY_DATABASE_URL
    gateway_env.pop("LIFECYCLE_DATA_DIR", None)
    files = scratch / "systemd-env"
    files.mkdir(exist_ok=True)
    env_file(files / "gateway.env", gateway_env)
    env_file(files / "robot.env", {"ROS_DOMAIN_ID": str(stack.domain(38))})
    owner, _ = Gateway.objects.get_or_create(name=GATEWAY)
    robot, _ = Robot.objects.update_or_create(name=ROBOT, defaults={
        "domain_id": stack.domain(38), "enabled": True, "gateway": owner, "auto_recover": True})
    name = f"lcdeploy{os.getpid()}-systemd"
    engine.run(["docker", "run", "-d", "--name", name, "--network", "host", "--ipc", "host", *systemd_flags(),
                "-v", f"{files}:/etc/lifecycle:ro", tag], timeout=60)
    try:
        stack.wait_for(lambda: gateways.status(GATEWAY).online, 60, f"gateway {GATEWAY} in the systemd container")
        yield name
    finally:
        logs = engine.run(["docker", "exec", name, "journalctl", "--no-pager", "-n", "200"], timeout=30, check=False)
        (engine.ARTIFACTS / "systemd-journal.log").write_text(logs.stdout + logs.stderr)
        engine.run(["docker", "rm", "-f", name], timeout=60, check=False)
        Robot.objects.filter(pk=robot.pk).update(enabled=False)
        left = engine.run(["docker", "ps", "-a", "-q", "--filter", f"name={name}"], timeout=30).stdout.strip()
        assert not left, f"container {name} was left"


def control(api: Client, action: str, process: str = PROCESS):
    return api.post(f"/api/v1/robots/{ROBOT}/processes/{process}", {"action": action},
                    content_type="application/json")


def main_pid(container: str) -> int:
    return int(engine.run(["docker", "exec", container, "systemctl", "show", UNIT, "-p", "MainPID", "--value"],
                          timeout=30).stdout)


def node(**fields) -> ManagedNode:
    return stack.wait_for(lambda: ManagedNode.objects.filter(key=NODE, **fields).first(), 60,
                          f"{NODE} with {fields}")


def test_a_unit_restart_brings_its_node_back_to_its_desired_state(api, robot_host):
    node(alive=True, supervised_by=PROCESS)
    activate_as_desired(api, ROBOT, NODE)
    before = main_pid(robot_host)

    asked = timezone.now()  # (the new instance may be seen before the restart's record is made)
    answer = control(api, "restart")
    assert answer.status_code == 200, answer.json()
    record = answer.json()["record"]
    assert (record["supervisor"], record["process"], record["action"], record["outcome"]) == (
        "systemd", PROCESS, "restart", "succeeded")
    assert record["old_pid"] == before and record["pid"] == main_pid(robot_host) != before
    # The demo robot ends on SIGINT with status 0, or by the signal while still starting up.
    assert record["exit_code"] == 0 or record["exit_signal"] in ("SIGINT", "SIGKILL"), record
    recovered = stack.wait_for(lambda: TransitionRecord.objects.filter(
        node__key=NODE, source="recovery", transition_label="activate", outcome="succeeded",
        requested_at__gte=asked).first(), 60, "the recovery's activate")
    assert recovered.result_state_label == "active"
    node(alive=True, state_label="active")


def test_stop_then_start_a_unit_and_what_is_not_its_robots_is_refused(api, robot_host):
    stopped = control(api, "stop")
    assert stopped.status_code == 200, stopped.json()
    assert engine.run(["docker", "exec", robot_host, "systemctl", "is-active", UNIT], timeout=30,
                      check=False).stdout.strip() == "inactive"
    node(alive=False)
    started = control(api, "start")
    assert started.status_code == 200, started.json()
    assert started.json()["record"]["pid"] == main_pid(robot_host)
    node(alive=True)
    # The gateway's own unit runs no node of the robot: not the robot's process, whatever a request says.
    ManagedNode.objects.filter(key=NODE).update(supervised_by="systemd:lifecycle-gateway.service")
    try:
        refused = control(api, "stop", "systemd:lifecycle-gateway.service")
        assert refused.json()["error"]["code"] == "unknown_process", refused.json()
    finally:
        ManagedNode.objects.filter(key=NODE).update(supervised_by=PROCESS)
    assert gateways.status(GATEWAY).online
