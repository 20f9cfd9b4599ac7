"""Scenario 3: 300 lifecycle nodes over 3 robots (ROS domains), 25 nodes per process.

Measures how long until the gateway has found them all and the API lists them alive (the
gateway reports them as facts; the ingest process stores them); ``GET /api/v1/nodes`` and the
fleet page at that size; bring-up of one robot for growing node counts (bringup.py); and the
resident memory of gateway, site and ingest process.
"""
from __future__ import annotations

import math
import time

from tests.benchmarks.bringup import measure_cold, measure_warm
from tests.benchmarks.harness import BenchContext, Stack
from tests.benchmarks.processes import BenchError, Child
from tests.benchmarks.profiling import profiled
from tests.benchmarks.report import ScenarioResult
from tests.benchmarks.system import cpu_seconds, loadavg, rss_mb

NAME = "scale"
TITLE = "3. Scale: 300 nodes on 3 robots; listing, fleet page, bring-up, memory"
ROBOTS = [("bench-s1", 123), ("bench-s2", 124), ("bench-s3", 125)]
DISCOVERY_TIMEOUT_S = 180.0
POLL_S = 0.25


class Sizes:
    def __init__(self, quick: bool) -> None:
        self.processes, self.per_process = (1, 20) if quick else (4, 25)
        self.bringup = [5, 10, 20] if quick else [10, 30, 100]
        self.page_samples = 10 if quick else 40

    @property
    def per_robot(self) -> int:
        return self.processes * self.per_process


def start_robots(stack: Stack, sizes: Sizes) -> list[Child]:
    return [
        stack.start_robot(f"{robot}-p{p}", domain, sizes.per_process, prefix=f"p{p}", wait=False)
        for robot, domain in ROBOTS
        for p in range(sizes.processes)
    ]


def watch_discovery(stack: Stack, robots: list[Child], total: int, result: ScenarioResult) -> None:
    """Poll until every node is listed alive with its state read; record when each stage ended."""
    launched = time.monotonic()
    gateway_cpu, ingest_cpu = cpu_seconds(stack.gateway.pid), cpu_seconds(stack.ingest.pid)
    marks: dict[str, float] = {}
    deadline = launched + DISCOVERY_TIMEOUT_S
    while not {"state read", "gateway"} <= marks.keys():
        now = time.monotonic()
        if now > deadline:
            raise BenchError(f"not all {total} nodes discovered within {DISCOVERY_TIMEOUT_S:g} s: {marks}, "
                             f"gateway says {stack.gateway_stats()}")
        if "ready" not in marks and all("demo robot ready" in r.output() for r in robots):
            marks["ready"] = now
        dead = [r.name for r in robots if not r.alive()]
        if dead:
            raise BenchError(f"robot processes died: {dead}")
        if "gateway" not in marks and stack.gateway_stats().get("nodes_alive", 0) >= total:
            marks["gateway"] = now
        listed = stack.nodes()
        alive = [n for n in listed if n["alive"]]
        if "listed" not in marks and len(alive) >= total:
            marks["listed"] = now
        if "listed" in marks and all(n["state"]["label"] != "unknown" for n in alive):
            marks["state read"] = now
        time.sleep(POLL_S)
    marks.setdefault("ready", marks["state read"])  # (only if a robot printed late)
    result.figure("robot processes ready, from launch", marks["ready"] - launched, "s")
    result.figure("gateway has all nodes, from launch", marks["gateway"] - launched, "s")
    result.figure("API lists all alive, from launch", marks["listed"] - launched, "s")
    result.figure("API lists all alive, from processes ready", max(marks["listed"] - marks["ready"], 0), "s")
    result.figure("all states read, from processes ready", max(marks["state read"] - marks["ready"], 0), "s")
    result.figure("gateway CPU during discovery", cpu_seconds(stack.gateway.pid) - gateway_cpu, "s")
    result.figure("ingest CPU during discovery", cpu_seconds(stack.ingest.pid) - ingest_cpu, "s")
    listed_after = max(marks["listed"] - marks["ready"], 0)
    result.check(f"{total} nodes listed, from processes ready", listed_after, "<= 10 s", listed_after <= 10, "s")


def idle_cpu(stack: Stack, seconds: float, total: int, result: ScenarioResult) -> None:
    """CPU the gateway, the site and the ingest process use with every node up and nothing happening."""
    pids = {"gateway": stack.gateway.pid, "site": stack.site.pid, "ingest": stack.ingest.pid}
    before = {k: cpu_seconds(pid) for k, pid in pids.items()}
    time.sleep(seconds)
    for name, pid in pids.items():
        share = (cpu_seconds(pid) - before[name]) / seconds * 100
        result.figure(f"{name} CPU at rest with {total} nodes", share, "% of a core")


def measure_pages(stack: Stack, samples: int, result: ScenarioResult) -> None:
    listing = result.new_series("GET /api/v1/nodes (all nodes, token)")
    overview = result.new_series("GET / fleet page (session)")
    for _ in range(samples):
        for series, client, path in ((listing, stack.api, "/api/v1/nodes"), (overview, stack.web, "/")):
            response = client.get(path)
            if response.status != 200:
                raise BenchError(f"GET {path} answered {response.status}")
            series.add(response.ms)
            time.sleep(0.05)
    result.check("node list median", listing.median, "< 300 ms", listing.median < 300, "ms")
    result.check("fleet page median", overview.median, "< 300 ms", overview.median < 300, "ms")


def run(ctx: BenchContext) -> ScenarioResult:
    result = ScenarioResult(NAME, TITLE, load_before=loadavg())
    sizes = Sizes(ctx.quick)
    total = sizes.per_robot * len(ROBOTS)
    result.notes.append(f"{total} nodes: {len(ROBOTS)} robots x {sizes.processes} processes x "
                        f"{sizes.per_process} nodes (demo robot --generic)")
    with ctx.stack(NAME, ROBOTS) as stack:
        processes = {"gateway": stack.gateway.pid, "site": stack.site.pid, "ingest": stack.ingest.pid}
        idle = {name: rss_mb(pid) for name, pid in processes.items()}
        robots = start_robots(stack, sizes)
        watch_discovery(stack, robots, total, result)
        time.sleep(1.0 if ctx.quick else 3.0)  # let the first state reads and pushes settle
        idle_cpu(stack, 3.0, total, result)
        with profiled(ctx, stack, NAME):
            measure_pages(stack, sizes.page_samples, result)
            peak = {name: rss_mb(pid) for name, pid in processes.items()}
            measure_cold(stack, ROBOTS[1][0], ROBOTS[2][0], sizes.bringup[-1], result)
            measure_warm(stack, ROBOTS[0][0], sizes.bringup, result)
        peak = {name: max(peak[name], rss_mb(pid)) for name, pid in processes.items()}
    result.figure("gateway RSS before robots started", idle["gateway"], "MB")
    result.figure("site (daphne) RSS before robots started", idle["site"], "MB")
    result.figure("ingest RSS before robots started", idle["ingest"], "MB")
    result.figure(f"ingest RSS at {total} nodes", peak["ingest"], "MB")
    result.figure(f"site side, daphne + ingest, at {total} nodes", peak["site"] + peak["ingest"], "MB")
    result.check(f"gateway RSS at {total} nodes", peak["gateway"], "< 200 MB", peak["gateway"] < 200, "MB")
    result.check(f"site RSS at {total} nodes", peak["site"], "< 150 MB", peak["site"] < 150, "MB")
    if any(math.isnan(mb) for mb in peak.values()):
        result.notes.append("a process was gone when its memory was read")
    return result
