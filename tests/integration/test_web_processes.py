"""The site served by several daphne processes on one socket (LIFECYCLE_WEB_PROCESSES=2,
lifecycle_site/web_processes.py), with the real gateway, robot, Redis and database: requests
are answered, a transition made through them is on record, a process that dies is
replaced while the other keeps answering, and stopping (or killing) the supervisor leaves no
daphne behind."""
from __future__ import annotations

import json
import os
import signal
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from lifecycle_site.api.models import ApiToken
from lifecycle_site.audit.models import TransitionRecord
from tests import stack
from tests.conftest import make_user
from tests.integration.conftest import register, wait_node

ROBOT = "web-processes-agv"
NODE = "lidar_driver"


def children(pid: int) -> list[int]:
    path = Path(f"/proc/{pid}/task/{pid}/children")
    return [int(p) for p in path.read_text().split()] if path.exists() else []


def call(base: str, path: str, token: str, body: dict | None = None) -> tuple[int, dict]:
    request = urllib.request.Request(
        base + path, data=json.dumps(body).encode() if body is not None else None,
        headers={"Authorization": f"Bearer {token}", "Content-Type": "application/json"},
        method="POST" if body is not None else "GET")
    try:
        with urllib.request.urlopen(request, timeout=20) as answer:  # a new connection each time
            return answer.status, json.loads(answer.read())
    except urllib.error.HTTPError as refused:
        return refused.code, json.loads(refused.read())


@pytest.fixture(scope="module")
def robot(gateway):
    register(ROBOT, stack.domain(34))
    process = stack.start_robot("web-processes-nodes", stack.domain(34), NODE)
    wait_node(None, f"{ROBOT}.{NODE}", alive=True, state="unconfigured")
    yield process
    process.stop()


@pytest.fixture
def site(gateway):
    process, base = stack.start_site("two-process-daphne", LIFECYCLE_WEB_PROCESSES="2")
    stack.wait_for(lambda: len(children(process.pid)) == 2, 20, "two daphne processes")
    yield process, base
    left = children(process.pid)
    process.stop()
    for pid in left:
        stack.wait_for(lambda pid=pid: not stack.pid_alive(pid), 20, f"daphne {pid} to end")


def test_requests_and_a_transition_through_them_are_answered_and_on_record(site, robot):
    process, base = site
    token = ApiToken.issue(make_user("wanda-web-processes", "operator"), "web-processes")[1]
    for _ in range(20):  # each on a new connection, which either process may accept
        status, body = call(base, "/api/v1/robots", token)
        assert status == 200, body
    key = f"{ROBOT}.{NODE}"
    status, body = call(base, f"/api/v1/nodes/{key}/transition", token, {"transition": "configure"})
    assert status == 200, body
    assert body["to"]["label"] == "inactive"
    record = TransitionRecord.objects.get(pk=body["record_id"])
    assert (record.transition_label, record.outcome, record.source) == ("configure", "succeeded", "api")
    status, body = call(base, f"/api/v1/nodes/{key}/transition", token, {"transition": "cleanup"})
    assert status == 200, body


def test_a_process_that_dies_is_replaced_while_the_other_answers(site):
    process, base = site
    token = ApiToken.issue(make_user("walt-web-processes", "operator"), "web-processes")[1]
    first, second = children(process.pid)
    os.kill(first, signal.SIGKILL)
    answered = 0
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and not (answered >= 10 and len(children(process.pid)) == 2):
        status, _ = call(base, "/api/v1/robots", token)
        assert status == 200  # the survivor took every new connection meanwhile
        answered += 1
    now = children(process.pid)
    assert len(now) == 2 and first not in now and second in now, now
    assert "daphne process %d ended" % first in process.output()


def test_a_killed_supervisor_takes_its_processes_with_it(gateway):
    process, _ = stack.start_site("two-process-daphne-killed", LIFECYCLE_WEB_PROCESSES="2")
    stack.wait_for(lambda: len(children(process.pid)) == 2, 20, "two daphne processes")
    left = children(process.pid)
    os.kill(process.pid, signal.SIGKILL)  # only the supervisor: not its process group
    try:
        for pid in left:
            stack.wait_for(lambda pid=pid: not stack.pid_alive(pid), 20, f"daphne {pid} to end with its supervisor")
    finally:
        process.stop(signal.SIGKILL)


def test_a_setting_it_cannot_serve_is_refused_by_name(gateway):
    process = stack.Process("bad-web-processes", [sys.executable, "-m", "lifecycle_site.serve", "-b", "127.0.0.1",
                                                  "-p", str(stack.free_port()), "lifecycle_site.asgi:application"],
                            stack.environment(LIFECYCLE_WEB_PROCESSES="two"), stack.log_dir())
    assert process.popen.wait(30) != 0
    assert "LIFECYCLE_WEB_PROCESSES='two': expected a whole number of processes" in process.output()
