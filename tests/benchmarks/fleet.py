"""Scenario: the fleet at size (issue 14). 1,000 lifecycle nodes on 10 robots (ROS domains
120-129, shared with the other scenarios: they run one after the other) behind 3 gateways,
robot processes of 50 nodes each, one site.

Measures, each with the load average when it was taken: how long until the API lists every
node alive with its state, from the robot processes ready; ``GET /api/v1/nodes`` and the fleet
page at that size (collapsed, one robot opened, every robot opened = the page before robots
collapsed) and the filter that finds a node in a collapsed robot; a group bring-up of one
robot (100 nodes) and of all robots at once (1,000), time per node and its growth; the
resident memory of each gateway, daphne and the ingest process; log records stored and relayed
per second while one node behind each gateway logs at a third of a little more than the target
rate (LOG_TARGET_PER_S; three Python senders at full speed would take more than the machine's
2 cores themselves), memory before, at the peak and after.
"""
from __future__ import annotations

import asyncio
import statistics
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace

from tests.benchmarks.bringup import RUN_WAIT_S, group_run, robot_nodes
from tests.benchmarks.flood import Relayed, count_records
from tests.benchmarks.harness import BenchContext, Stack
from tests.benchmarks.probe import LineProcess
from tests.benchmarks.processes import BenchError, Child
from tests.benchmarks.profiling import profiled
from tests.benchmarks.report import ScenarioResult
from tests.benchmarks.system import cpu_seconds, loadavg, rss_mb
from tests.benchmarks.web import Http

NAME = "fleet"
TITLE = "Fleet: 1,000 nodes on 10 robots behind 3 gateways; listing, pages, bring-up, memory, logs"
ROBOTS = [(f"bench-f{i}", 120 + i) for i in range(10)]
GATEWAYS = 3  # robot i is behind gateway i % 3 (the first one is the stack's own)
DISCOVERY_TIMEOUT_S = 300.0
DRAIN_TIMEOUT_S = 120.0
STABLE_S = 2.0
FLAT_MB = 5.0  # "memory flat once buffers are full": growth from the first drop to the flood's end
LOG_TARGET_PER_S = 20_000  # records stored and relayed per second, from 3 gateways at once
LOG_OFFERED_PER_S = 24_000  # what the three senders offer together
POLL_S = 0.5


class Sizes:
    def __init__(self, quick: bool) -> None:
        self.robots = ROBOTS[:6] if quick else ROBOTS
        self.processes, self.per_process = (1, 20) if quick else (2, 50)
        self.page_samples = 8 if quick else 30
        self.flood_s = 5.0 if quick else 10.0

    @property
    def per_robot(self) -> int:
        return self.processes * self.per_process

    @property
    def total(self) -> int:
        return self.per_robot * len(self.robots)


def with_load(result: ScenarioResult, name: str, value: float, unit: str) -> None:
    """A figure and, beside it, the 1-minute load average when it was taken."""
    result.figure(name, value, unit)
    result.figure(f"  load average then ({name[:40]})", loadavg()[0], "")


class Fleet:
    """The stack plus the two more gateways; which robots each watches."""

    def __init__(self, stack: Stack, sizes: Sizes) -> None:
        self.stack, self.sizes = stack, sizes
        self.behind: dict[str, list[tuple[str, int]]] = {}
        for i, robot in enumerate(sizes.robots):
            self.behind.setdefault(self.gateway_name(i % GATEWAYS), []).append(robot)

    def gateway_name(self, index: int) -> str:
        return self.stack.gateway_name if index == 0 else f"{self.stack.gateway_name}-{index}"

    def start_gateways(self) -> None:
        for name, robots in self.behind.items():
            if name != self.stack.gateway_name:
                self.stack.add_gateway(name, robots)

    def gateways(self) -> dict[str, Child]:
        main = self.stack.gateway
        assert main is not None
        return {self.stack.gateway_name: main, **self.stack.more_gateways}

    def stats(self, name: str) -> dict:
        return self.stack.gateway_stats(None if name == self.stack.gateway_name else name)

    def memory(self) -> dict[str, float]:
        stack = self.stack
        assert stack.site is not None and stack.ingest is not None
        found = {f"gateway {name}": rss_mb(child.pid) for name, child in self.gateways().items()}
        return {**found, "site": rss_mb(stack.site.pid), "ingest": rss_mb(stack.ingest.pid)}


def start_robots(fleet: Fleet) -> list[Child]:
    sizes = fleet.sizes
    return [fleet.stack.start_robot(f"{robot}-p{p}", domain, sizes.per_process, prefix=f"{robot[6:]}p{p}", wait=False)
            for robot, domain in sizes.robots for p in range(sizes.processes)]


def watch_discovery(fleet: Fleet, robots: list[Child], result: ScenarioResult) -> None:
    """Poll until every node is listed alive with its state read, from the processes ready."""
    stack, total = fleet.stack, fleet.sizes.total
    launched = time.monotonic()
    cpu_before = {name: cpu_seconds(child.pid) for name, child in fleet.gateways().items()}
    marks: dict[str, float] = {}
    deadline = launched + DISCOVERY_TIMEOUT_S
    while "state read" not in marks:
        now = time.monotonic()
        if now > deadline:
            raise BenchError(f"not all {total} nodes listed with states within {DISCOVERY_TIMEOUT_S:g} s: "
                             f"{marks}; gateways say {[fleet.stats(n).get('nodes_alive') for n in fleet.gateways()]}")
        if "ready" not in marks and all("demo robot ready" in r.output() for r in robots):
            marks["ready"] = now
            with_load(result, "robot processes ready, from launch", now - launched, "s")
        dead = [r.name for r in robots if not r.alive()]
        if dead:
            raise BenchError(f"robot processes died: {dead}")
        for name, child in fleet.gateways().items():
            if not child.alive():
                raise BenchError(f"gateway {name} ended during discovery:\n{child.output()[-1500:]}")
        alive = [n for n in stack.nodes() if n["alive"]]
        if "listed" not in marks and len(alive) >= total:
            marks["listed"] = now
        if "listed" in marks and all(n["state"]["label"] != "unknown" for n in alive):
            marks["state read"] = now
        time.sleep(POLL_S)
    ready = marks.get("ready", marks["state read"])
    with_load(result, "API lists all alive, from processes ready", max(marks["listed"] - ready, 0), "s")
    listed = max(marks["state read"] - ready, 0)
    with_load(result, "API lists all alive with states, from processes ready", listed, "s")
    for name, child in fleet.gateways().items():
        result.figure(f"gateway {name} CPU during discovery", cpu_seconds(child.pid) - cpu_before[name], "s")
    result.check(f"{total} nodes on {len(fleet.sizes.robots)} robots behind {GATEWAYS} gateways listed alive "
                 "with states, from processes ready", listed, "< 15 s", listed < 15, "s")


def measure_pages(fleet: Fleet, result: ScenarioResult) -> None:
    """The node list and the fleet page: collapsed (as it opens), one robot opened, every robot
    opened (what the page was before robots collapsed); the filter of a collapsed robot's node."""
    stack, sizes = fleet.stack, fleet.sizes
    names = [robot for robot, _ in sizes.robots]
    one = names[len(names) // 2]
    wanted = robot_nodes(stack, one, sizes.per_robot)[1][-1].strip("/")
    paths = {
        "GET /api/v1/nodes (all nodes, token)": (stack.api, "/api/v1/nodes"),
        "GET / fleet page (session)": (stack.web, "/"),
        "GET / fleet page, one robot opened": (stack.web, f"/?open={one}"),
        "GET / fleet page, every robot opened (as before collapsing)": (stack.web, "/?open=" + ",".join(names)),
        "GET /fleet/find: a node by name in the collapsed robots": (
            stack.web, f"/fleet/find?q={wanted}&robots={','.join(names)}"),
    }
    series = {label: result.new_series(label) for label in paths}
    for _ in range(sizes.page_samples):
        for label, (client, path) in paths.items():
            response = client.get(path)
            if response.status != 200:
                raise BenchError(f"GET {path} answered {response.status}")
            series[label].add(response.ms)
            time.sleep(0.05)
    found = stack.web.get(paths["GET /fleet/find: a node by name in the collapsed robots"][1]).body.decode()
    if sizes.total > 300 and f"/{wanted}<" not in found:
        raise BenchError(f"the fleet page's filter did not find {wanted} on {one}")
    load = loadavg()[0]
    for label in paths:
        result.figure(f"  load average then ({label[:40]})", load, "")
    listing, page = series["GET /api/v1/nodes (all nodes, token)"], series["GET / fleet page (session)"]
    result.check(f"GET /api/v1/nodes at {sizes.total} nodes, median", listing.median, "< 100 ms",
                 listing.median < 100, "ms")
    result.check(f"fleet page at {sizes.total} nodes, median", page.median, "< 100 ms", page.median < 100, "ms")


def idle_cpu(fleet: Fleet, robots: list[Child], seconds: float, result: ScenarioResult) -> None:
    """CPU at rest of gateways, site, ingest, and of all robot processes together (the load
    the other figures are taken under)."""
    stack = fleet.stack
    assert stack.site is not None and stack.ingest is not None
    pids = {f"gateway {n}": c.pid for n, c in fleet.gateways().items()}
    pids.update(site=stack.site.pid, ingest=stack.ingest.pid)
    before = {k: cpu_seconds(pid) for k, pid in pids.items()}
    robots_before = sum(cpu_seconds(r.pid) for r in robots)
    time.sleep(seconds)
    for name, pid in pids.items():
        with_load(result, f"{name} CPU at rest", (cpu_seconds(pid) - before[name]) / seconds * 100, "% of a core")
    robots_cpu = (sum(cpu_seconds(r.pid) for r in robots) - robots_before) / seconds * 100
    with_load(result, f"{len(robots)} robot processes together, CPU at rest", robots_cpu, "% of a core")


def all_robots(fleet: Fleet, operation: str, names: dict[str, list[str]]) -> float:
    """``operation`` on every robot at once (one group run each, side by side): wall seconds."""
    api = fleet.stack.api
    # One connection per robot: a keep-alive connection carries one request at a time.
    clients = {robot: SimpleNamespace(api=Http(api.host, api.port, token=api.token)) for robot in names}
    began = time.perf_counter()
    with ThreadPoolExecutor(len(names)) as pool:
        futures = [pool.submit(group_run, clients[robot], robot, operation, nodes)  # type: ignore[arg-type]
                   for robot, nodes in names.items()]
        for future in futures:
            future.result(timeout=RUN_WAIT_S + 30)
    return time.perf_counter() - began


def measure_bringup(fleet: Fleet, result: ScenarioResult) -> None:
    """Group bring-up of one robot (all its nodes) and of every robot at once: time per node."""
    stack, sizes = fleet.stack, fleet.sizes
    names = {robot: robot_nodes(stack, robot, sizes.per_robot)[1] for robot, _ in sizes.robots}
    first = next(iter(names))
    with_load(result, f"cold: first group bringup of all {sizes.total} nodes at once",
              all_robots(fleet, "bringup", names), "s")
    all_robots(fleet, "reset", names)
    small = []
    for _ in range(2):
        small.append(group_run(stack, first, "bringup", names[first])[0])
        group_run(stack, first, "reset", names[first])
    with_load(result, f"group bringup of {sizes.per_robot} nodes (one robot)", statistics.median(small), "s")
    large = all_robots(fleet, "bringup", names)
    with_load(result, f"group bringup of {sizes.total} nodes ({len(names)} robots at once)", large, "s")
    all_robots(fleet, "reset", names)
    per_small, per_large = statistics.median(small) / sizes.per_robot, large / sizes.total
    result.figure(f"time per node at {sizes.per_robot}", per_small * 1000, "ms")
    result.figure(f"time per node at {sizes.total}", per_large * 1000, "ms")
    growth = per_large / per_small
    result.check(f"group bring-up: time per node at {sizes.total} / at {sizes.per_robot}", growth, "<= 1.2 x",
                 growth <= 1.2, "x")


def check_memory(fleet: Fleet, peak: dict[str, float], result: ScenarioResult) -> None:
    for name, robots in fleet.behind.items():
        nodes = len(robots) * fleet.sizes.per_robot
        mb = peak[f"gateway {name}"]
        result.figure(f"gateway {name} RSS with {nodes} nodes", mb, "MB")
        per_300 = mb * 300 / max(nodes, 300)  # (below 300 nodes: the RSS itself)
        result.check(f"gateway {name} RSS per 300 nodes", per_300, "< 200 MB", per_300 < 200, "MB")
    result.check(f"site (daphne) RSS at {fleet.sizes.total} nodes", peak["site"], "< 150 MB", peak["site"] < 150, "MB")
    result.check(f"ingest RSS at {fleet.sizes.total} nodes", peak["ingest"], "< 100 MB", peak["ingest"] < 100, "MB")


# (monotonic time, RSS MB by process, log records dropped so far by gateway)
Sample = tuple[float, dict[str, float], dict[str, int]]


def dropped(fleet: Fleet) -> dict[str, int]:
    return {name: fleet.stats(name).get("logs_dropped", 0) for name in fleet.gateways()}


def observe(fleet: Fleet, samples: list[Sample], stop: threading.Event) -> None:
    while not stop.is_set():
        samples.append((time.monotonic(), fleet.memory(), dropped(fleet)))
        stop.wait(0.25)


def wait_drained(fleet: Fleet, relayed: dict[str, Relayed]) -> tuple[int, float]:
    """Until the stored and relayed counts stop moving with nothing left in any gateway's
    buffer or outbox: (records stored ever, when the counts last moved)."""
    deadline = time.monotonic() + DRAIN_TIMEOUT_S
    last_seen, last_change = (-1, -1), time.monotonic()
    while time.monotonic() < deadline:
        stored = fleet.stack.ingest_stats()["logs_stored"]
        seen = (stored, sum(r.records for r in relayed.values()))
        stats = [fleet.stats(name) for name in fleet.gateways()]
        if seen != last_seen:
            last_seen, last_change = seen, time.monotonic()
        elif time.monotonic() - last_change > STABLE_S and not any(
                s.get("logs_buffered") or s.get("outbox", {}).get("log_batches") for s in stats):
            return stored, last_change
        time.sleep(0.1)
    raise BenchError(f"log records were still on their way {DRAIN_TIMEOUT_S:g} s after the flood: {last_seen}")


async def flood_measure(fleet: Fleet, flooders: dict[str, LineProcess], result: ScenarioResult) -> None:
    stack, seconds = fleet.stack, fleet.sizes.flood_s
    relayed = {key: Relayed() for key in flooders}
    stop = asyncio.Event()
    readies = {key: asyncio.Event() for key in flooders}
    listeners = [asyncio.create_task(count_records(stack.web, key, relayed[key], readies[key], stop))
                 for key in flooders]
    await asyncio.wait_for(asyncio.gather(*(e.wait() for e in readies.values())), 20)
    await asyncio.sleep(1.0)
    stored_before, drops_before = stack.ingest_stats()["logs_stored"], dropped(fleet)
    received_before = sum(fleet.stats(n).get("logs_received", 0) for n in fleet.gateways())
    memory_before = fleet.memory()
    samples: list[Sample] = []
    done = threading.Event()
    observer = threading.Thread(target=observe, args=(fleet, samples, done), daemon=True)
    observer.start()
    assert stack.site is not None and stack.ingest is not None
    pids = {f"gateway {n}": c.pid for n, c in fleet.gateways().items()}
    pids.update(site=stack.site.pid, ingest=stack.ingest.pid)
    pids.update({f"sender {key}": f.pid for key, f in flooders.items()})
    cpu_before = {k: cpu_seconds(pid) for k, pid in pids.items()}
    began = time.monotonic()
    answers = await asyncio.gather(*(asyncio.to_thread(f.call, "flood", seconds + 30, seconds=seconds,
                                                       rate=LOG_OFFERED_PER_S / len(flooders))
                                     for f in flooders.values()))
    load = loadavg()[0]
    stored_after, stored_done = await asyncio.to_thread(wait_drained, fleet, relayed)
    busy_s = max(stored_done - began, 1e-3)
    cpu = {k: (cpu_seconds(pid) - cpu_before[k]) / busy_s * 100 for k, pid in pids.items()}
    done.set()
    observer.join(5)
    stop.set()
    await asyncio.gather(*listeners)
    memory_after = fleet.memory()
    sent = sum(a["sent"] for a in answers)
    flood_s = max(a["seconds"] for a in answers)
    stored = stored_after - stored_before
    relayed_n = sum(r.records for r in relayed.values())
    relayed_s = max(max(r.last for r in relayed.values()) - began, flood_s)
    stored_rate = stored / max(stored_done - began, flood_s)
    relay_rate = relayed_n / relayed_s
    received = sum(fleet.stats(n).get("logs_received", 0) for n in fleet.gateways()) - received_before
    result.figure(f"log records sent by {len(flooders)} nodes (one per gateway) at once", sent, "records")
    result.figure("  sent per second", sent / flood_s, "/s")
    result.figure("  received by the gateways", received, "records")
    result.figure("  lost before the gateways (DDS: sent - received)", sent - received, "records")
    result.figure("  received per second", received / flood_s, "/s")
    result.figure("  dropped by the gateways' bounded buffers",
                  sum(dropped(fleet).values()) - sum(drops_before.values()), "records")
    result.figure("  stored in the database (ingest)", stored, "records")
    result.figure("  relayed to the log consoles' WebSockets", relayed_n, "records")
    result.figure("  load average at the flood's end", load, "")
    for process, percent in cpu.items():  # where the 2 cores went until the last record was stored
        result.figure(f"  {process} CPU, flood and drain", percent, "% of a core")
    for process, mb in memory_before.items():
        peak = max((s[1][process] for s in samples), default=float("nan"))
        result.figure(f"{process} RSS before the flood", mb, "MB")
        result.figure(f"{process} RSS peak during the flood", peak, "MB")
        result.figure(f"{process} RSS after draining", memory_after[process], "MB")
    result.check("log records stored per second, 3 gateways at once", stored_rate, ">= 20,000 /s",
                 stored_rate >= LOG_TARGET_PER_S, "/s")
    result.check("log records relayed per second, 3 gateways at once", relay_rate, ">= 20,000 /s",
                 relay_rate >= LOG_TARGET_PER_S, "/s")
    ended = began + flood_s
    for name in fleet.gateways():
        full = next((s[0] for s in samples if s[2].get(name, 0) > drops_before.get(name, 0)), None)
        since = full if full is not None and full < ended else began + flood_s / 2
        window = [s[1][f"gateway {name}"] for s in samples if since <= s[0] <= ended]
        growth = max(window) - window[0] if window else float("nan")
        what = "once its buffer was full" if full is not None and full < ended else "in the flood's 2nd half"
        result.check(f"gateway {name} RSS growth {what}", growth, f"<= {FLAT_MB:g} MB", growth <= FLAT_MB, "MB")


def flood_all(ctx: BenchContext, fleet: Fleet, result: ScenarioResult) -> None:
    """One node behind each gateway (on its first robot) logs as fast as it can, all at once."""
    stack = fleet.stack
    flooders: dict[str, LineProcess] = {}
    try:
        for i, robots in enumerate(fleet.behind.values()):
            robot, domain = robots[0]
            node = f"log_flooder_{i}"
            flooders[f"{robot}.{node}"] = LineProcess(stack, f"flooder-{i}", "tests.benchmarks.flooder",
                                                      str(domain), node)
        stack.wait_nodes(list(flooders), 120, state="unconfigured")
        with profiled(ctx, stack, f"{NAME}-flood"):
            asyncio.run(flood_measure(fleet, flooders, result))
    finally:
        for flooder in flooders.values():
            flooder.close()


def run(ctx: BenchContext) -> ScenarioResult:
    result = ScenarioResult(NAME, TITLE, load_before=loadavg())
    sizes = Sizes(ctx.quick)
    result.notes.append(f"{sizes.total} nodes: {len(sizes.robots)} robots x {sizes.processes} processes x "
                        f"{sizes.per_process} nodes (demo robot --generic), robot i behind gateway i % {GATEWAYS}")
    first = [robot for i, robot in enumerate(sizes.robots) if i % GATEWAYS == 0]
    with ctx.stack(NAME, first) as stack:
        fleet = Fleet(stack, sizes)
        fleet.start_gateways()
        idle = fleet.memory()
        robots = start_robots(fleet)
        watch_discovery(fleet, robots, result)
        time.sleep(1.0 if ctx.quick else 3.0)  # let the first state reads and pushes settle
        idle_cpu(fleet, robots, 3.0, result)
        with profiled(ctx, stack, NAME):
            measure_pages(fleet, result)
            peak = fleet.memory()
            measure_bringup(fleet, result)
        peak = {name: max(mb, fleet.memory()[name]) for name, mb in peak.items()}
        check_memory(fleet, peak, result)
        flood_all(ctx, fleet, result)
    for process, mb in idle.items():
        result.figure(f"{process} RSS before robots started", mb, "MB")
    if ctx.profile_dir is not None:
        result.notes.append("py-spy samples the stack's first gateway, daphne and ingest (not gateways 2 and 3)")
    return result
