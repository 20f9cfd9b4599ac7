"""A run's verdict is final: a gateway frozen (SIGSTOP) in the middle of a bring-up, whose run the
site has meanwhile declared failed (silent past LIFECYCLE_RUN_ORPHAN_AFTER), drives no further
node once it is continued, and its late report leaves the run failed."""
from __future__ import annotations

import time

import pytest
from django.core.management import call_command

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import Gateway, GroupRun, ManagedNode, Robot
from tests import stack
from tests.integration.conftest import register, wait_node

NAME, ROBOT, NAMESPACE = "cell-v", "verdict-agv", "/verdict"
NODES = ("flaky_node", "camera_driver", "lidar_driver")  # the bring-up order
ORPHAN_AFTER_S = 12.0  # the ingest process's LIFECYCLE_RUN_ORPHAN_AFTER in this test
SLOW_CONFIGURE_S = 6.0  # flaky_node's configure: the step the gateway is frozen in


def key(node: str) -> str:
    return f"{ROBOT}.{NAMESPACE.strip('/')}.{node}"


@pytest.fixture
def quick_verdicts(ingest):
    """The site's ingest process with a short LIFECYCLE_RUN_ORPHAN_AFTER, in place of the
    session's (started again afterwards, whatever happens)."""
    ingest.stop()
    process = None
    try:
        process = stack.start_ingest("ingest-quick-verdicts", LIFECYCLE_RUN_ORPHAN_AFTER=str(ORPHAN_AFTER_S))
        stack.wait_for(lambda: "ingest is running" in process.output() or not process.alive(), 30,
                       "the ingest process to start")
        assert process.alive(), process.output()
        yield process
    finally:
        if process is not None:
            process.stop()
        ingest.start()


@pytest.fixture
def cell(live_db, quick_verdicts, tmp_path):
    path = tmp_path / "cell.env"
    call_command("add_gateway", NAME, env_file=str(path))
    env = dict(line.split("=", 1) for line in path.read_text().splitlines() if line and not line.startswith("#"))
    register(ROBOT, stack.domain(24), namespace=NAMESPACE, gateway=NAME)
    processes: list[stack.Process] = []
    try:
        processes.append(stack.start_robot("verdict-agv-nodes", stack.domain(24), ",".join(NODES),
                                           "flaky_node.failure_mode:=slow_configure",
                                           f"flaky_node.slow_seconds:={SLOW_CONFIGURE_S}", namespace=NAMESPACE))
        gateway = stack.start_gateway(NAME, **env)
        processes.append(gateway)
        for node in NODES:
            wait_node(None, key(node), alive=True, state="unconfigured", timeout=30)
        for position, node in enumerate(NODES, start=1):  # one tier per node, flaky_node first
            ManagedNode.objects.filter(key=key(node)).update(order=position)
        yield gateway
    finally:
        for process in processes:
            process.stop()
        Robot.objects.filter(name=ROBOT).delete()
        Gateway.objects.filter(name=NAME).delete()


def test_a_gateway_continued_after_the_verdict_drives_no_node_and_the_run_stays_failed(api, cell):
    response = api.post(f"/api/v1/robots/{ROBOT}/operations", {"operation": "bringup", "timeout": 20},
                        content_type="application/json")
    assert response.status_code == 202, response.json()
    run_id = response.json()["run"]["id"]
    stack.wait_for(lambda: GroupRun.objects.get(id=run_id).status == GroupRun.Status.RUNNING, 10, "the run running")
    time.sleep(1.0)  # flaky_node is configuring (SLOW_CONFIGURE_S) when the gateway stops
    with stack.frozen(cell.pid):
        frozen_at = time.monotonic()
        run = stack.wait_for(lambda: (r := GroupRun.objects.get(id=run_id)).done and r, ORPHAN_AFTER_S + 30,
                             "the site's verdict on the run of the frozen gateway")
        assert run.status == GroupRun.Status.FAILED and "could not finish" in run.message, (run.status, run.message)
        print(f"verdict {time.monotonic() - frozen_at:.1f} s after the freeze: {run.message}")
        verdict = run.finished
        time.sleep(2.0)
    # Continued: the gateway finishes the step it was in (flaky_node's configure), then reports.
    stack.wait_for(lambda: stack.facts_read(NAME) and TransitionRecord.objects.filter(
        run_id=run_id, node__key=key("flaky_node"), transition_label="configure").exists(), 30,
        "the step under way at the freeze on record")
    time.sleep(SLOW_CONFIGURE_S)  # what today's gateway went on with has had time to happen
    stack.wait_for(lambda: stack.facts_read(NAME), 20, "the gateway's facts read by the ingest process")
    run = GroupRun.objects.get(id=run_id)
    after = [(r.node_name, r.transition_label, r.outcome, f"{(r.requested_at - verdict).total_seconds():+.1f} s")
             for r in TransitionRecord.objects.filter(run_id=run_id, requested_at__gte=verdict).order_by("id")]
    states = {n: ManagedNode.objects.get(key=key(n)).state_label for n in NODES}
    print(f"after the verdict: run {run.status} ({run.message}); steps {after}; states {states}")
    assert run.status == GroupRun.Status.FAILED and not after, (run.status, run.message, after, states)
    assert states == {"flaky_node": "inactive", "camera_driver": "unconfigured", "lidar_driver": "unconfigured"}, \
        states
    assert "could not finish" in run.message and "after this verdict" in run.message, run.message
    # The one step under way at the freeze is on record (requested before the verdict).
    steps = [(r.node_name, r.transition_label) for r in TransitionRecord.objects.filter(run_id=run_id)]
    assert steps == [(f"{NAMESPACE}/flaky_node", "configure")], steps
