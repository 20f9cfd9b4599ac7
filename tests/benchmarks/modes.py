"""Scenario 12 (issue 29): robot modes.

1. Apply a mode that changes 50 nodes of one robot, back and forth between "parked" (all 50
   unconfigured) and "working" (all 50 active, one parameter set on each before activation;
   three readiness predicates): from the API request until the robot is ready in it, as the API
   says (in the mode: no drift; ready: every predicate holds), polled every 50 ms; and until its
   run ended. system_modes takes 2.2-4 s for each change of one node (its issue #98).
2. Drift made behind the product's back -> shown on the robot's Modes page: the benchmark's own
   rclpy process deactivates one node of the robot in mode "working" (and activates it again);
   from the node's transition event (stamped by that process) to the page's WebSocket message
   showing the difference (and, after the activation, none).
"""
from __future__ import annotations

import asyncio
import json
import time

from tests.benchmarks.harness import BenchContext, Stack
from tests.benchmarks.probe import RosProbe
from tests.benchmarks.processes import BenchError, run_manage
from tests.benchmarks.profiling import profiled
from tests.benchmarks.report import ScenarioResult
from tests.benchmarks.system import loadavg
from tests.benchmarks.web import received, ws_connect

NAME = "modes"
TITLE = "12. Robot modes: apply a mode changing 50 nodes -> ready; drift -> shown on the Modes page"
ROBOT, DOMAIN, PREFIX = "bench-modes", 130, "mode_node"
NODES = 50
READY_TARGET_S = 2.0
DRIFT_P99_TARGET_MS = 500.0
POLL_S = 0.05
APPLY_TIMEOUT_S = 60.0
DRIFTED, IN_MODE = "1 difference", "Every node is as the mode says"


def define_modes(stack: Stack, names: list[str]) -> None:
    """The two modes, written as an admin would (the benchmark's token is an operator's)."""
    working = {n: {"state": "active", "parameters": {"gain": 2.5}} for n in names}
    parked = {n: {"state": "unconfigured"} for n in names}
    ready = [{"node": n, "state": "active"} for n in names[:3]]
    code = (
        "from lifecycle_site.fleet.models import Robot\nfrom lifecycle_site.modes.models import Mode\n"
        f"robot = Robot.objects.get(name={ROBOT!r})\n"
        f"for name, nodes, ready in (('working', {working!r}, {ready!r}), ('parked', {parked!r}, [])):\n"
        "    mode, _ = Mode.objects.update_or_create(name=name, defaults={'nodes': nodes, 'ready_when': ready})\n"
        "    mode.robots.add(robot)\n"
    )
    run_manage(stack.env, "shell", "-c", code)


def apply(stack: Stack, mode: str) -> tuple[float, float]:
    """Apply; seconds until the API says the robot is ready in it, and until its run ended."""
    began = time.monotonic()
    answer = stack.api.post_json(f"/api/v1/robots/{ROBOT}/modes/{mode}/apply", {"policy": "continue"})
    if answer.status not in (200, 202):
        raise BenchError(f"apply {mode} answered {answer.status}: {answer.body[:300]!r}")
    run_id = answer.json()["run"]["id"]
    ready_at = run_done_at = None
    while time.monotonic() - began < APPLY_TIMEOUT_S and (ready_at is None or run_done_at is None):
        now = time.monotonic()
        if ready_at is None:
            drift = stack.api.get(f"/api/v1/robots/{ROBOT}/drift").json()
            if drift.get("mode") == mode and drift.get("in_mode") and drift.get("ready"):
                ready_at = now
        if run_done_at is None:
            run = stack.api.get(f"/api/v1/runs/{run_id}").json()["run"]
            if run["status"] not in ("queued", "running"):
                if run["status"] != "succeeded":
                    raise BenchError(f"apply {mode}: its run ended {run['status']}: {run['message']}")
                run_done_at = now
        time.sleep(POLL_S)
    if ready_at is None or run_done_at is None:
        raise BenchError(f"{mode}: not ready within {APPLY_TIMEOUT_S:g} s")
    return ready_at - began, run_done_at - began


async def drift_to_page(stack: Stack, probe: RosProbe, fqn: str, rounds: int) -> tuple[list[float], list[float]]:
    """Deactivate (drift) and activate (none) ``fqn`` from another process, ``rounds`` times; the
    milliseconds from each end event to the Modes page's message saying so."""
    arrivals: list[tuple[float, str]] = []
    stop, ready = asyncio.Event(), asyncio.Event()

    async def listen() -> None:
        async with ws_connect(stack.web, f"/ws/robots/{ROBOT}/modes/") as ws:
            ready.set()
            async for arrived, message in received(ws, stop):
                if isinstance(message, str) and 'id="modes-live"' in message:
                    arrivals.append((arrived, DRIFTED if DRIFTED in message else IN_MODE if IN_MODE in message else ""))

    task = asyncio.create_task(listen())
    await asyncio.wait_for(ready.wait(), 15)
    await asyncio.sleep(1.0)
    await asyncio.to_thread(probe.call, "events")
    arrivals.clear()
    for _ in range(rounds):
        for transition_id in (4, 3):  # deactivate, activate
            await asyncio.to_thread(probe.change, fqn, transition_id)
            await asyncio.sleep(0.6)
    await asyncio.sleep(1.0)
    stop.set()
    await task
    events = (await asyncio.to_thread(probe.call, "events"))["events"]
    drifted, back = [], []
    for published, _start, goal in events:
        if goal not in ("inactive", "active"):
            continue
        wanted = DRIFTED if goal == "inactive" else IN_MODE
        shown = next((at for at, what in arrivals if at >= published and what == wanted), None)
        if shown is None:
            raise BenchError(f"the Modes page never showed {wanted!r} after {fqn} became {goal}")
        (drifted if goal == "inactive" else back).append((shown - published) * 1000)
    return drifted, back


def run(ctx: BenchContext) -> ScenarioResult:
    result = ScenarioResult(NAME, TITLE, load_before=loadavg())
    rounds = 2 if ctx.quick else 5
    drift_rounds = 8 if ctx.quick else 40
    names = [f"/{PREFIX}_{i:03d}" for i in range(NODES)]
    with ctx.stack(NAME, [(ROBOT, DOMAIN)]) as stack:
        stack.start_robot("robot", DOMAIN, generic=NODES, prefix=PREFIX)
        stack.wait_nodes([f"{ROBOT}.{n.strip('/')}" for n in names], 60, state="unconfigured")
        define_modes(stack, names)
        ready = result.new_series(f"apply 'working' ({NODES} nodes: configure, set parameter, activate) -> ready",
                                  "s")
        done = result.new_series("apply 'working' -> its run ended", "s")
        parked = result.new_series(f"apply 'parked' ({NODES} nodes: deactivate, cleanup) -> in the mode", "s")
        with profiled(ctx, stack, NAME):
            for _ in range(rounds):
                to_ready, to_done = apply(stack, "working")
                ready.add(to_ready)
                done.add(to_done)
                parked.add(apply(stack, "parked")[0])
            apply(stack, "working")
            probe = RosProbe(stack, DOMAIN)
            fqn = names[10]
            probe.call("watch", node=fqn)
            drifted, back = asyncio.run(drift_to_page(stack, probe, fqn, drift_rounds))
            probe.close()
    shown = result.new_series("drift (another tool's deactivate) -> Modes page shows it")
    for value in drifted:
        shown.add(value)
    cleared = result.new_series("back (its activate) -> Modes page shows no difference")
    for value in back:
        cleared.add(value)
    result.check("apply 50 nodes -> ready, median", ready.median, f"< {READY_TARGET_S:g} s",
                 ready.median < READY_TARGET_S, "s")
    p99 = shown.summary()["p99"]
    result.check("drift -> page, p99", p99, f"< {DRIFT_P99_TARGET_MS:g} ms", p99 < DRIFT_P99_TARGET_MS, "ms")
    result.notes.append("system_modes for comparison: 2.2-4 s per change of one node (ros2/system_modes#98); "
                        f"here {NODES} nodes change in one run. Readiness: 3 node-state predicates.")
    result.notes.append(json.dumps({"rounds": rounds, "drift_rounds": drift_rounds}))
    return result
