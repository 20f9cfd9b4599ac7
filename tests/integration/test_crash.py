"""Crashes are crashes: a node process that dies during a transition, or by itself, is said to be
lost at once (not a 'timed out' after the service timeout, nor 20 s later when its DDS lease
runs out), in the answer, the audit log, the API and the page; a new instance of it is recorded
as such, its state and parameters read from the new process; its absence stays on its timeline."""
from __future__ import annotations

import asyncio
import time

import pytest
from asgiref.sync import async_to_sync
from channels.layers import get_channel_layer

from lifecycle_site.audit.models import TransitionRecord
from ros_gateway.shared import protocol
from tests import stack
from tests.integration.conftest import register, transition, wait_node

ROBOT = "it-crash"
KEY = f"{ROBOT}.crash.flaky_node"
# The request's own service timeout: the old code answered only after it ("Timed out").
REQUEST_TIMEOUT_S = 10
BOUND_S = 3.0


@pytest.fixture(scope="module")
def domain(gateway) -> int:
    # A namespace of its own: another module's robot on the same domain does not own these nodes.
    register(ROBOT, stack.domain(27), namespace="/crash")
    return stack.domain(27)


def start_flaky(name: str, domain_id: int, mode: str) -> stack.Process:
    return stack.start_robot(name, domain_id, "flaky_node", f"flaky_node.failure_mode:={mode}", namespace="/crash")


def records(outcome: str, since) -> list[TransitionRecord]:
    return list(TransitionRecord.objects.filter(node__key=KEY, outcome=outcome, requested_at__gte=since))


def test_a_process_that_dies_during_activate_is_lost_at_once(api, domain):
    process = start_flaky("crash-1", domain, "crash")
    try:
        wait_node(api, KEY, alive=True, state="unconfigured", timeout=30)
        # The parameters as an open page shows them (and the gateway keeps them).
        shown = {p["name"]: p["value"] for p in api.get(f"/api/v1/nodes/{KEY}/parameters").json()["parameters"]}
        assert shown["failure_mode"] == "crash"
        assert transition(api, KEY, "configure").status_code == 200
        began = time.monotonic()
        response = transition(api, KEY, "activate", timeout=REQUEST_TIMEOUT_S)
        took = time.monotonic() - began
        print(f"[crash] activate answered {took:.2f} s after the request: {response.json()}")
        error = response.json()["error"]
        assert took < BOUND_S, f"answered after {took:.1f} s"
        assert response.status_code == 422 and error["code"] == "process_lost" and error["state"] is None, error
        assert "process ended during activate" in error["message"], error["message"]
        assert "segmentation fault" in error["message"], "the node's own FATAL line is in the reason"
        record = TransitionRecord.objects.get(id=error["record_id"])
        assert (record.outcome, record.transition_label, record.start_state_label, record.source) == (
            "process_lost", "activate", "inactive", "api")
        assert record.completed_at is not None and record.duration_ms < BOUND_S * 1000
        assert record.error == error["message"]
        node = api.get(f"/api/v1/nodes/{KEY}").json()
        assert (node["alive"], node["gone_reason"], node["process"]["status"]) == (False, "process_lost", "lost")
        assert node["process"]["since"] and node["transitions"] == []
        page = api.get(f"/nodes/{KEY}/").content.decode()
        assert "Process lost at " in page and "Transition in progress" not in page
        # One record of the loss: the transition's own (discovery does not add another).
        time.sleep(1.0)
        assert TransitionRecord.objects.filter(node__key=KEY, outcome="process_lost").count() == 1
    finally:
        process.stop()


def test_a_new_instance_is_recorded_with_its_state_and_parameters_read_again(api, domain):
    """After the crash above: the restarted process (failure_mode none) is a new instance."""
    node_group = protocol.node_group(KEY)

    async def restart_and_listen() -> list[dict]:
        layer = get_channel_layer()
        channel = await layer.new_channel()
        await layer.group_add(node_group, channel)
        since = time.time()
        process = await asyncio.to_thread(start_flaky, "crash-2", domain, "none")
        try:
            seen: list[dict] = []
            while not any(m["type"] == "node.parameters" and any(c["name"] == "failure_mode" for c in m["changes"])
                          for m in seen):
                assert time.time() - since < 30, f"no parameters pushed; saw {[m['type'] for m in seen]}"
                seen.append(await asyncio.wait_for(layer.receive(channel), 30))
            return seen
        finally:
            process_box.append(process)

    process_box: list[stack.Process] = []
    began = time.monotonic()
    asked = TransitionRecord.objects.order_by("-requested_at").first().requested_at
    try:
        messages = async_to_sync(restart_and_listen)()
        pushed = next(m for m in messages if m["type"] == "node.parameters"
                      and any(c["name"] == "failure_mode" for c in m["changes"]))
        assert {"name": "failure_mode", "old": "crash", "new": "none"} in pushed["changes"], pushed
        wait_node(api, KEY, alive=True, state="unconfigured", timeout=30)
        restarted = stack.wait_for(lambda: records("process_restarted", asked), 10, "the restart's record")
        print(f"[crash] new instance recorded {time.monotonic() - began:.2f} s after its start began")
        record = restarted[0]
        assert (record.start_state_id, record.result_state_label, record.source) == (None, "unconfigured", "external")
        assert "new instance" in record.error
        node = api.get(f"/api/v1/nodes/{KEY}").json()
        assert (node["alive"], node["gone_reason"], node["process"]["status"]) == (True, "", "restarted")
        values = {p["name"]: p["value"] for p in api.get(f"/api/v1/nodes/{KEY}/parameters").json()["parameters"]}
        assert values["failure_mode"] == "none"
        page = api.get(f"/nodes/{KEY}/").content.decode()
        assert "Process restarted (new instance) at " in page
    finally:
        for process in process_box:
            process.stop()


def test_a_process_killed_between_transitions_is_lost_and_its_return_recorded(api, domain):
    process = start_flaky("crash-3", domain, "none")
    try:
        wait_node(api, KEY, alive=True, state="unconfigured", timeout=30)
        assert transition(api, KEY, "configure").status_code == 200
        since = TransitionRecord.objects.filter(node__key=KEY).order_by("-requested_at").first().requested_at
        away_before = api.get(f"/api/v1/nodes/{KEY}/timeline", {"window": "hour"}).json()["absences"]
        process.kill()
        killed = time.monotonic()
        wait_node(api, KEY, alive=False, timeout=15)
        took = time.monotonic() - killed
        print(f"[crash] a killed process shown lost after {took:.2f} s")
        assert took < BOUND_S, f"lost after {took:.1f} s (the DDS lease, not the process, told)"
        lost = stack.wait_for(lambda: records("process_lost", since), 5, "the loss's record")
        assert len(lost) == 1 and lost[0].source == "external" and lost[0].start_state_label == "inactive"
        assert "exited" in lost[0].error and lost[0].completed_at is not None
        node = api.get(f"/api/v1/nodes/{KEY}").json()
        assert (node["gone_reason"], node["process"]["status"]) == ("process_lost", "lost")
    finally:
        process.stop()
    process = start_flaky("crash-4", domain, "none")
    try:
        wait_node(api, KEY, alive=True, state="unconfigured", timeout=30)
        stack.wait_for(lambda: records("process_restarted", since), 10, "the restart's record")
        assert len(records("process_lost", since)) == 1
        # The absence stays on the node's timeline after its return.
        timeline = api.get(f"/api/v1/nodes/{KEY}/timeline", {"window": "hour"}).json()
        assert timeline["absences"] == away_before + 1, timeline
        assert "process lost" in [s["state"] for s in timeline["segments"]]
        assert [s["state"] for s in timeline["segments"]][-1] == "unconfigured"
    finally:
        process.stop()
