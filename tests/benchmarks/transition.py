"""Scenario 1: one lifecycle transition, three ways, side by side on the same node.

(a) ``POST /api/v1/nodes/{id}/transition`` to daphne over a keep-alive connection with a
    bearer token (site -> Redis -> gateway -> DDS and back);
(b) a direct ChangeState call from a warm rclpy process (the floor); beside it (b2) the same
    process reading the state first, as the gateway does before every change (its safety
    promise), which is the floor of what the gateway does;
(c) a fresh process per call, as ``ros2 lifecycle set`` does (start, discover, call, exit).

Beside (a), the HTTP layer alone on the same connection: a static file from daphne, and a
token-authenticated read of the robot list (database only: no gateway, no ROS), to show
where (a)'s time goes.

The three are interleaved cycle by cycle (configure, activate, deactivate, cleanup), so a
disturbance of the machine hits all of them alike.
"""
from __future__ import annotations

import subprocess
import time

from tests.benchmarks.harness import BenchContext, Stack
from tests.benchmarks.probe import RosProbe
from tests.benchmarks.processes import PYTHON, ROOT, BenchError, wait_for
from tests.benchmarks.profiling import profiled
from tests.benchmarks.report import ScenarioResult, Series
from tests.benchmarks.system import loadavg
from tests.benchmarks.web import Http

NAME = "transition"
TITLE = "1. Transition latency: API vs direct rclpy (floor) vs fresh process per call"
DOMAIN = 120
ROBOT = "bench-tr"
NODE = "bench_node_000"
CYCLE = [("configure", 1), ("activate", 3), ("deactivate", 4), ("cleanup", 2)]
# Quiet time after each call, so the gateway's follow-up work (events, audit, pushes) of one
# call does not overlap the next measurement.
PAUSE_S = 0.08
# A refused or failed API call is counted and the node put back in step; more than this many
# and the scenario fails.
MAX_API_FAILURES = 3
STATIC_FILE = "/static/img/favicon.svg"
# From each state back to unconfigured, directly (transition ids).
BACK_TO_UNCONFIGURED = {"active": [4, 2], "inactive": [2], "unconfigured": []}


def api_cycle(api: Http, key: str, total: Series | None, inner: Series | None) -> None:
    for label, _ in CYCLE:
        response = api.transition(key, label)
        if response.status != 200:
            raise BenchError(f"API {label} on {key} answered {response.status}: {response.body[:300]!r}")
        if total is not None and inner is not None:
            total.add(response.ms)
            inner.add(response.json()["duration_ms"])
        time.sleep(PAUSE_S)


def http_cycle(api: Http, static: Series, read: Series) -> None:
    for _ in CYCLE:
        for series, path in ((static, STATIC_FILE), (read, "/api/v1/robots")):
            response = api.get(path)
            if response.status != 200:
                raise BenchError(f"GET {path} answered {response.status}")
            series.add(response.ms)
        time.sleep(PAUSE_S)


def realign(probe: RosProbe, fqn: str) -> None:
    """Bring the node back to unconfigured (the start of a cycle) after a failed API call."""
    label = probe.call("state", node=fqn)["label"]
    if label not in BACK_TO_UNCONFIGURED:
        raise BenchError(f"{fqn} is {label}; cannot put it back in step")
    for transition_id in BACK_TO_UNCONFIGURED[label]:
        probe.change(fqn, transition_id)


def direct_cycle(probe: RosProbe, fqn: str, series: Series | None, check: bool = False) -> None:
    for _, transition_id in CYCLE:
        answer = probe.change(fqn, transition_id, check)
        if series is not None:
            series.add(answer["ms"])
        time.sleep(PAUSE_S)


def fresh_cycle(env: dict[str, str], fqn: str, series: Series) -> None:
    for label, transition_id in CYCLE:
        began = time.perf_counter()
        done = subprocess.run(
            [PYTHON, str(ROOT / "tests" / "benchmarks" / "one_shot.py"), str(DOMAIN), fqn, str(transition_id)],
            cwd=ROOT, env=env, capture_output=True, timeout=60,
        )
        if done.returncode != 0:
            raise BenchError(f"fresh-process {label} failed ({done.returncode}): {done.stderr[-500:]!r}")
        series.add((time.perf_counter() - began) * 1000)
        time.sleep(PAUSE_S)


def settled_audit(stack: Stack, timeout: float = 30.0) -> dict[str, int]:
    """The audit records by source, once their counts stayed the same for a second."""
    last: list[dict[str, int]] = []

    def stable() -> dict[str, int] | None:
        now = stack.ingest_stats()["audit_records"]
        same = bool(last) and last[0] == now
        last[:] = [now]
        return now if same else None

    return wait_for(stable, timeout, "the audit records to settle", 1.0)


def run(ctx: BenchContext) -> ScenarioResult:
    result = ScenarioResult(NAME, TITLE, load_before=loadavg())
    cycles, fresh_cycles = (8, 1) if ctx.quick else (40, 3)
    a = result.new_series("(a) API POST .../transition")
    b = result.new_series("(b) direct rclpy ChangeState (floor)")
    b2 = result.new_series("(b2) direct get_state + ChangeState")
    c = result.new_series("(c) fresh process per call")
    inner = result.new_series("gateway's own ChangeState call, of (a)")
    static = result.new_series("HTTP floor: static file from daphne")
    read = result.new_series("token GET /api/v1/robots (site only: DB, no gateway)")
    key, fqn = f"{ROBOT}.{NODE}", f"/{NODE}"
    with ctx.stack(NAME, [(ROBOT, DOMAIN)]) as stack:
        stack.start_robot("robot", DOMAIN, generic=1, prefix="bench_node")
        stack.wait_nodes([key], 60, state="unconfigured")
        probe = RosProbe(stack, DOMAIN)
        api_cycle(stack.api, key, None, None)  # warm-up: clients matched, code paths loaded
        direct_cycle(probe, fqn, None)
        fresh_every = max(cycles // fresh_cycles, 1)
        failures: list[str] = []
        with profiled(ctx, stack, NAME):
            for i in range(cycles):
                try:
                    api_cycle(stack.api, key, a, inner)
                except BenchError as exc:
                    failures.append(str(exc))
                    if len(failures) > MAX_API_FAILURES:
                        raise
                    time.sleep(0.5)
                    realign(probe, fqn)
                http_cycle(stack.api, static, read)
                direct_cycle(probe, fqn, b)
                direct_cycle(probe, fqn, b2, check=True)
                if i % fresh_every == 0 and len(c.values) < 4 * fresh_cycles:
                    fresh_cycle(stack.env, fqn, c)
        probe.close()
        audit = settled_audit(stack)
    result.figure("API calls refused or failed (node put back in step, cycle skipped)", len(failures))
    # Every transition leaves one audit record: the site writes an API call's from the gateway's
    # reply, the ingest process a direct call's (seen by the gateway as external) from the stream.
    result.figure("API transitions answered 200 (warm-up included)", len(a.values) + len(CYCLE))
    result.figure("audit records of API calls", audit.get("api", 0))
    result.figure("direct transitions (b, b2, c, warm-up, realignments)", probe.changes + len(c.values))
    result.figure("audit records of direct transitions (external, stored by ingest)", audit.get("external", 0))
    result.notes.extend(f"API call failed: {f[:300]}" for f in failures)
    a_over_b = result.figure("ratio a/b (median)", a.median / b.median, "x")
    c_over_a = result.figure("ratio c/a (median)", c.median / a.median, "x")
    result.figure("ratio a/b2 (median; b2 checks the state first, as the gateway does)", a.median / b2.median, "x")
    result.figure("API overhead over the gateway's ChangeState (median)", a.median - inner.median, "ms")
    result.check("a/b, API within 1.5x of the floor", a_over_b, "<= 1.5", a_over_b <= 1.5, "x")
    result.check("c/a, API 50x faster than fresh process", c_over_a, ">= 50", c_over_a >= 50, "x")
    return result
