"""The gateway as a robot's Docker supervisor, with the real engine: a container of the product's
image runs a lifecycle node (host network and IPC, as ROS 2 containers on a robot run); the gateway,
on the same host, finds the node's process in that container (its cgroup) and names it
"docker:<container>"; a restart from the API goes through the Docker Engine API, the record names
the container and the old process's end, and the node's new instance is driven back to its
desired state (active). Stop and start; refusals for what the gateway did not attribute."""
from __future__ import annotations

import os

import pytest
from django.test import Client
from django.utils import timezone

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import Gateway, ManagedNode, Robot
from tests import stack
from tests.deploy import engine

ROBOT = "docker-agv"
NODE = f"{ROBOT}.lidar_driver"


@pytest.fixture(scope="module")
def container(image, docker_engine):
    """The robot's container (its name of this run's own), removed at the end whatever happened."""
    name = f"lcdeploy{os.getpid()}-drivers"
    # Host network and IPC, as root like the gateway: Fast DDS's shared-memory segments are its user's only.
    engine.run(["docker", "run", "-d", "--name", name, "--network", "host", "--ipc", "host", "--user", "0:0",
                "-e", f"ROS_DOMAIN_ID={stack.domain(37)}", "-e", "ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST",
                "--stop-timeout", "5", image, "python", "-m", "ros_gateway.demo.robot", "--nodes", "lidar_driver"],
               timeout=60)
    try:
        yield name
    finally:
        engine.run(["docker", "rm", "-f", name], timeout=60, check=False)
        left = engine.run(["docker", "ps", "-a", "-q", "--filter", f"name={name}"], timeout=30).stdout.strip()
        assert not left, f"container {name} was left"


@pytest.fixture(scope="module")
def robot(gateway, container):  # (the gateway on the host, as root: it reads /proc and the socket)
    owner, _ = Gateway.objects.get_or_create(name="local")
    made, _ = Robot.objects.update_or_create(name=ROBOT, defaults={
        "domain_id": stack.domain(37), "enabled": True, "gateway": owner, "auto_recover": True})
    process = f"docker:{container}"
    stack.wait_for(lambda: ManagedNode.objects.filter(key=NODE, alive=True, supervised_by=process).exists(), 60,
                   f"the node found in container {container}")
    yield made
    Robot.objects.filter(pk=made.pk).update(enabled=False)
    Robot.objects.get(pk=made.pk).save()


def control(api: Client, process: str, action: str):
    return api.post(f"/api/v1/robots/{ROBOT}/processes/{process}", {"action": action},
                    content_type="application/json")


def container_pid(name: str) -> int:
    return int(engine.run(["docker", "inspect", "-f", "{{.State.Pid}}", name], timeout=30).stdout)


def node(**fields) -> ManagedNode:
    return stack.wait_for(lambda: ManagedNode.objects.filter(key=NODE, **fields).first(), 60,
                          f"{NODE} with {fields}")


def activate_as_desired(api: Client, robot: str, key: str) -> None:
    """The node made active, its desired state active (which a restart's recovery brings it back to)."""
    for transition in ("configure", "activate"):
        answer = api.post(f"/api/v1/nodes/{key}/transition", {"transition": transition},
                          content_type="application/json")
        assert answer.status_code == 200, answer.json()
    ManagedNode.objects.filter(key=key).update(desired_state="active")
    Robot.objects.get(name=robot).save()  # the gateway learns the desired state
    stack.wait_for(lambda: ManagedNode.objects.filter(key=key, state_label="active").exists(), 30, f"{key} active")


def test_a_container_restart_brings_its_node_back_to_its_desired_state(api, robot, container):
    process = f"docker:{container}"
    listing = api.get(f"/api/v1/robots/{ROBOT}/processes").json()["processes"]
    (shown,) = [p for p in listing if p["name"] == process]
    assert (shown["supervisor"], shown["nodes"], shown["status"]) == ("docker", ["/lidar_driver"], "running")
    activate_as_desired(api, ROBOT, NODE)
    before = container_pid(container)

    asked = timezone.now()  # (the new instance may be seen before the restart's record is made)
    answer = control(api, process, "restart")
    assert answer.status_code == 200, answer.json()
    record = answer.json()["record"]
    assert (record["supervisor"], record["action"], record["outcome"], record["requested_by"]) == (
        "docker", "restart", "succeeded", "ivan-operator")
    assert record["process"] == process and container in record["message"]
    assert record["old_pid"] == before and record["pid"] == container_pid(container) != before
    # The demo robot ends on SIGTERM: the old process's end is on record.
    assert record["exit_code"] is not None or record["exit_signal"], record
    recovered = stack.wait_for(lambda: TransitionRecord.objects.filter(
        node__key=NODE, source="recovery", transition_label="activate", outcome="succeeded",
        requested_at__gte=asked).first(), 60, "the recovery's activate")
    assert recovered.result_state_label == "active"
    assert node(alive=True, state_label="active").supervised_by == process


def test_stop_then_start_a_container(api, robot, container):
    process = f"docker:{container}"
    stopped = control(api, process, "stop")
    assert stopped.status_code == 200, stopped.json()
    assert stopped.json()["record"]["action"] == "stop"
    assert engine.run(["docker", "inspect", "-f", "{{.State.Running}}", container], timeout=30).stdout.strip() == \
        "false"
    again = control(api, process, "stop")
    assert again.status_code == 409 and again.json()["error"]["code"] == "process_state"
    node(alive=False)
    started = control(api, process, "start")  # the gateway still knows the container its node ran in
    assert started.status_code == 200, started.json()
    assert started.json()["record"]["pid"] == container_pid(container)
    node(alive=True)


def test_a_container_the_gateway_did_not_attribute_is_refused(api, robot, container, image):
    other = f"lcdeploy{os.getpid()}-bystander"
    engine.run(["docker", "run", "-d", "--name", other, image, "sleep", "300"], timeout=60)
    try:
        answer = control(api, f"docker:{other}", "stop")
        assert answer.status_code == 404 and answer.json()["error"]["code"] == "unknown_process"
        # Named by a forged fact, it is still not the gateway's to touch.
        ManagedNode.objects.filter(key=NODE).update(supervised_by=f"docker:{other}")
        answer = control(api, f"docker:{other}", "stop")
        assert answer.json()["error"]["code"] == "unknown_process", answer.json()
        running = engine.run(["docker", "inspect", "-f", "{{.State.Running}}", other], timeout=30).stdout.strip()
        assert running == "true"
    finally:
        ManagedNode.objects.filter(key=NODE).update(supervised_by=f"docker:{container}")
        engine.run(["docker", "rm", "-f", other], timeout=60, check=False)
