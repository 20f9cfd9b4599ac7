"""Many gateways, one site: two gateways with robots in ROS domains of their own, each with
its own Redis user and no database; one killed and restarted; the ingest process stopped for
a minute; Redis gone for a minute. Nothing the robots did may be lost."""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from django.core.management import call_command

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import Gateway, LogRecord, ManagedNode, Robot
from tests import stack
from tests.integration.conftest import register, transition, wait_node

CELLS = {"cell-a": ("gw-a1", 20), "cell-b": ("gw-b1", 21)}


def gateway_env(name: str, tmp: Path) -> dict[str, str]:
    """What ``manage.py add_gateway`` hands the cell's operator, as the process's environment."""
    path = tmp / f"{name}.env"
    call_command("add_gateway", name, env_file=str(path))
    assert oct(path.stat().st_mode & 0o777) == "0o600"
    env = dict(line.split("=", 1) for line in path.read_text().splitlines() if line and not line.startswith("#"))
    assert env["LIFECYCLE_GATEWAY_NAME"] == name and f"gw-{name}:" in env["REDIS_URL"]
    return env


class Cell:
    def __init__(self, name: str, env: dict[str, str]) -> None:
        self.name, self.env = name, env
        self.robot, offset = CELLS[name]
        self.domain = stack.domain(offset)
        self.process = self.start()

    def start(self) -> stack.Process:
        return stack.start_gateway(self.name, **self.env)

    def key(self, node: str) -> str:
        return f"{self.robot}.{node}"


@pytest.fixture(scope="module")
def cells(redis_server, live_db, ingest, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("gateways")
    made = {}
    robots = []
    for name, (robot, offset) in CELLS.items():
        env = gateway_env(name, tmp)
        register(robot, stack.domain(offset), gateway=name)
        made[name] = Cell(name, env)
        robots.append(stack.start_robot(f"{robot}-nodes", stack.domain(offset), "lidar_driver,camera_driver"))
    for cell in made.values():
        for node in ("lidar_driver", "camera_driver"):
            wait_node(None, cell.key(node), alive=True, state="unconfigured", timeout=30)
    yield made
    for process in robots:
        process.stop()
    for cell in made.values():
        cell.process.stop()
    # Later tests (the gateway banner among them) see a fleet without these cells.
    Robot.objects.filter(gateway__name__in=CELLS).delete()
    Gateway.objects.filter(name__in=CELLS).delete()


def gateways(api) -> dict[str, dict]:
    response = api.get("/api/v1/gateways")
    assert response.status_code == 200, response.content
    return {g["name"]: g for g in response.json()["gateways"]}


def test_each_gateway_finds_its_robots_and_carries_out_their_transitions(api, cells):
    for cell in cells.values():
        response = transition(api, cell.key("lidar_driver"), "configure")
        assert response.status_code == 200, response.json()
        record = TransitionRecord.objects.get(id=response.json()["record_id"])
        who = (record.robot_name, record.outcome, record.requested_by_name)
        assert who == (cell.robot, "succeeded", "ivan-operator")
        assert ManagedNode.objects.get(key=cell.key("lidar_driver")).state_label == "inactive"
    listed = gateways(api)
    for name, cell in cells.items():
        assert listed[name]["online"], listed[name]
        assert cell.robot in [r["name"] if isinstance(r, dict) else r for r in listed[name]["robots"]]


def test_gateways_never_open_the_database(cells):
    """Every gateway of the test run is started with a database it cannot open."""
    assert not Path(stack.GATEWAY_DATABASE_URL.removeprefix("sqlite:///")).parent.exists()
    for cell in cells.values():
        output = cell.process.output()
        assert "unable to open database" not in output and "OperationalError" not in output, output[-3000:]


def test_a_killed_gateway_takes_only_its_robots_offline_and_comes_back(api, cells):
    a, b = cells["cell-a"], cells["cell-b"]
    b.process.kill()
    killed = time.monotonic()
    stack.wait_for(lambda: not gateways(api)["cell-b"]["online"], 10, "cell-b shown offline")
    assert time.monotonic() - killed < 3 + 2, "offline later than the heartbeat bound allows"
    began = time.monotonic()
    response = transition(api, b.key("camera_driver"), "configure")
    assert time.monotonic() - began < 1.0, "a command for an offline gateway must fail at once"
    assert response.status_code == 503, response.json()
    error = response.json()["error"]
    assert error["code"] == "gateway_offline" and "cell-b" in error["message"], error
    record = TransitionRecord.objects.get(id=error["record_id"])
    assert record.outcome == "rejected" and "cell-b" in record.error
    assert gateways(api)["cell-a"]["online"]
    assert transition(api, a.key("camera_driver"), "configure").status_code == 200

    b.process = b.start()  # the killed instance's lease runs out; the new one takes over
    stack.wait_for(lambda: gateways(api)["cell-b"]["online"], 20, "cell-b back online")
    response = stack.wait_for(
        lambda: (r := transition(api, b.key("camera_driver"), "configure")).status_code != 503 and r, 20,
        "a command through the restarted cell-b")
    assert response.status_code == 200, response.json()


def external(domain: int, node: str, transition_id: int) -> None:
    """Another tool (like ``ros2 lifecycle set``) changes the node's state."""
    done = subprocess.run([sys.executable, "tests/integration/ros_call.py", str(domain), node, str(transition_id)],
                          env=stack.environment(), capture_output=True, text=True, timeout=30)
    assert "success" in done.stdout, done.stdout + done.stderr


def cycle(cell: Cell, node: str, rounds: int) -> int:
    """Configure/activate/deactivate/cleanup by another tool; returns how many transitions."""
    count = 0
    for _ in range(rounds):
        for transition_id in (1, 3, 4, 2):
            external(cell.domain, f"/{node}", transition_id)
            count += 1
    return count


def test_nothing_is_lost_while_the_ingest_process_is_stopped_for_a_minute(api, cells, ingest):
    a = cells["cell-a"]
    wait_node(api, a.key("camera_driver"), alive=True, state="inactive")
    node = ManagedNode.objects.get(key=a.key("camera_driver"))
    records_before = TransitionRecord.objects.filter(node=node, source="external").count()
    logs_before = LogRecord.objects.filter(node=node).count()
    ingest.stop()
    stopped = time.monotonic()
    try:
        external(a.domain, "/camera_driver", 2)  # cleanup: back to unconfigured
        made = 1 + cycle(a, "camera_driver", 2)
        external(a.domain, "/camera_driver", 1)  # ends inactive
        made += 1
        time.sleep(max(0.0, 60 - (time.monotonic() - stopped)))
        node.refresh_from_db()
        assert TransitionRecord.objects.filter(node=node, source="external").count() == records_before
    finally:
        ingest.start()
    stack.wait_for(
        lambda: TransitionRecord.objects.filter(node=node, source="external").count() == records_before + made,
        30, f"{made} external transitions recorded after the ingest process came back")
    wait_node(api, a.key("camera_driver"), alive=True, state="inactive")
    # What the node logged meanwhile (each transition says so) is stored too.
    stack.wait_for(lambda: LogRecord.objects.filter(node=node).count() >= logs_before + made, 30,
                   f"at least {made} log lines of the node stored")
    gateway = Gateway.objects.get(name="cell-a")
    assert gateway.facts_lost == 0


def test_a_gateway_that_loses_redis_for_a_minute_delivers_what_happened_meanwhile(api, cells, redis_server, ingest):
    b = cells["cell-b"]
    wait_node(api, b.key("lidar_driver"), alive=True)
    node = ManagedNode.objects.get(key=b.key("lidar_driver"))
    before = TransitionRecord.objects.filter(node=node, source="external").count()
    redis_server.stop()
    stopped = time.monotonic()
    try:
        state = node.state_label
        made = 0
        if state == "inactive":
            external(b.domain, "/lidar_driver", 2)
            made += 1
        made += cycle(b, "lidar_driver", 2)
        time.sleep(max(0.0, 60 - (time.monotonic() - stopped)))
        assert b.process.alive(), "the gateway must keep running without Redis"
    finally:
        redis_server.start()
    stack.wait_for(
        lambda: TransitionRecord.objects.filter(node=node, source="external").count() == before + made,
        60, f"{made} transitions made while Redis was down, recorded once it was back")
    stack.wait_for(lambda: gateways(api)["cell-b"]["online"], 30, "cell-b online again")
    response = stack.wait_for(
        lambda: (r := transition(api, b.key("lidar_driver"), "configure")).status_code != 503 and r, 30,
        "a command through cell-b after Redis came back")
    assert response.status_code == 200, response.json()
    assert os.path.exists(stack.log_dir() / "cell-b.log")
