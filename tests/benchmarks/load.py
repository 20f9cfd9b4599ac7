"""Scenario 7: the site under a control room's load. 50 WebSocket clients (half on the fleet
page, half on node pages) stay connected while API clients send 100 requests/s for 60 s, ten
of them transitions each second (ten nodes, each walked through configure, activate,
deactivate, cleanup by its own client, so no request waits for another on the same node).

Reported: every API answer's latency (reads and transitions apart), errors (any answer that
is not 2xx, any failed connection), sockets dropped before the end, how late each client's
requests were against their schedule (the load generator's own lag), "transition requested ->
new state on its node page" for every transition, and the resident memory of daphne, the
gateway and the ingest process before and after.
"""
from __future__ import annotations

import asyncio
import threading
import time
from dataclasses import dataclass, field

from tests.benchmarks.harness import BenchContext, Stack
from tests.benchmarks.profiling import profiled
from tests.benchmarks.push import NODE_BADGE
from tests.benchmarks.report import ScenarioResult, Series, percentile
from tests.benchmarks.system import loadavg, tree_cpu_seconds, tree_rss_mb
from tests.benchmarks.web import Http, received, ws_connect

NAME = "load"
TITLE = "7. Load: 50 WebSocket clients + 100 API requests/s (10 transitions/s) for 60 s"
DOMAIN = 126  # shared with the quiet scenario; scenarios run one after the other
ROBOT = "bench-load"
NODES = 10
CYCLE = ["configure", "activate", "deactivate", "cleanup"]
GOAL = {"configure": "inactive", "activate": "active", "deactivate": "inactive", "cleanup": "unconfigured"}
SOCKETS = 50
REQUESTS_PER_S = 100
TRANSITIONS_PER_S = 10
# Threads sharing the read load, each its own keep-alive connection, so the offered rate holds
# while answers take up to READERS / read rate (~0.2 s); beyond, the lag figure says so.
READERS = 18
API_P99_TARGET_MS = 100.0
SHOWN_P99_TARGET_MS = 500.0  # transition requested -> its new state on the node page


@dataclass
class Tally:
    """What every client thread adds to, under one lock."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    errors: list[str] = field(default_factory=list)
    requested: dict[str, list[tuple[float, str]]] = field(default_factory=dict)  # node -> (sent, goal)

    def error(self, what: str) -> None:
        with self.lock:
            self.errors.append(what)


def paced(rate: float, seconds: float, stop: threading.Event, lag: Series, start: float, phase: float = 0.0):
    """Yield at ``rate`` per second for ``seconds`` from ``start`` + ``phase`` (monotonic); a late
    tick is recorded and sent at once."""
    interval = 1.0 / rate
    tick = 0
    while not stop.is_set():
        due = start + phase + tick * interval
        if due - start >= seconds:
            return
        now = time.monotonic()
        if now < due:
            time.sleep(due - now)
        else:
            lag.add((now - due) * 1000)
        yield
        tick += 1


def phases(clients: int, rate: float) -> list[float]:
    """Each client's offset into its interval, spread evenly: clients that poll on their own
    do not all ask in the same millisecond (in lockstep, 18 reads arrived together every
    200 ms and waited for each other)."""
    return [i / (clients * rate) for i in range(clients)]


def read_paths(keys: list[str]) -> list[str]:
    paths = ["/api/v1/nodes", "/api/v1/robots", "/api/v1/gateways", "/api/v1/transitions?limit=20"]
    paths += [f"/api/v1/nodes/{key}" for key in keys[:3]]
    paths += [f"/api/v1/nodes/{key}/logs?limit=20" for key in keys[:3]]
    return paths


def reader(stack: Stack, paths: list[str], rate: float, seconds: float, stop: threading.Event, series: Series,
           lag: Series, tally: Tally, start: float, phase: float) -> None:
    api = Http("127.0.0.1", stack.web_port, token=stack.token, timeout=10)
    try:
        for i, _ in enumerate(paced(rate, seconds, stop, lag, start, phase)):
            path = paths[i % len(paths)]
            try:
                answer = api.get(path)
            except OSError as exc:
                tally.error(f"GET {path}: {type(exc).__name__}: {exc}")
                continue
            series.add(answer.ms)
            if answer.status != 200:
                tally.error(f"GET {path}: {answer.status} {answer.body[:200]!r}")
    finally:
        api.close()


def operator(stack: Stack, key: str, seconds: float, stop: threading.Event, series: Series, lag: Series,
             tally: Tally, start: float, phase: float) -> None:
    """One node's transitions, one a second, round the cycle."""
    api = Http("127.0.0.1", stack.web_port, token=stack.token, timeout=30)
    sent: list[tuple[float, str]] = []
    try:
        for i, _ in enumerate(paced(TRANSITIONS_PER_S / NODES, seconds, stop, lag, start, phase)):
            label = CYCLE[i % len(CYCLE)]
            began = time.monotonic()
            try:
                answer = api.transition(key, label)
            except OSError as exc:
                tally.error(f"{key} {label}: {type(exc).__name__}: {exc}")
                continue
            series.add(answer.ms)
            if answer.status != 200:
                tally.error(f"{key} {label}: {answer.status} {answer.body[:200]!r}")
                continue
            sent.append((began, GOAL[label]))
    finally:
        api.close()
        with tally.lock:
            tally.requested[key] = sent


@dataclass
class Sockets:
    opened: int = 0
    dropped: list[str] = field(default_factory=list)
    messages: int = 0
    shown: dict[str, list[tuple[float, str]]] = field(default_factory=dict)  # node -> (arrived, state)


async def watch(stack: Stack, path: str, key: str | None, sockets: Sockets, ready: asyncio.Event,
                stop: asyncio.Event, total: int) -> None:
    try:
        async with ws_connect(stack.web, path) as ws:
            sockets.opened += 1
            if sockets.opened == total:
                ready.set()
            async for arrived, message in received(ws, stop):
                sockets.messages += 1
                if key is not None and isinstance(message, str) and 'id="node-state"' in message:
                    match = NODE_BADGE.search(message)
                    if match:
                        sockets.shown.setdefault(key, []).append((arrived, match.group(1)))
    except Exception as exc:  # noqa: BLE001 - whatever ends a socket early is what we count
        sockets.dropped.append(f"{path}: {type(exc).__name__}: {exc}")
        ready.set()


def show_latencies(requested: dict[str, list[tuple[float, str]]], shown: dict[str, list[tuple[float, str]]],
                   series: Series) -> int:
    """For each transition, the first time its node page showed the goal state after it was
    sent; returns how many were never shown."""
    missing = 0
    for key, sent in requested.items():
        arrivals = shown.get(key, [])
        for began, goal in sent:
            first = next((t for t, state in arrivals if t >= began and state == goal), None)
            if first is None:
                missing += 1
            else:
                series.add((first - began) * 1000)
    return missing


def run(ctx: BenchContext) -> ScenarioResult:
    """The load once per site set-up, side by side: one daphne process (as installed, and on a
    device) and two (LIFECYCLE_WEB_PROCESSES=2, for a site host with two cores or more)."""
    result = ScenarioResult(NAME, TITLE, load_before=loadavg())
    for processes in (ctx.web_processes,) if ctx.web_processes is not None else (1, 2):
        measure_site(ctx, result, processes)
    return result


def measure_site(ctx: BenchContext, result: ScenarioResult, processes_wanted: int) -> None:
    seconds = 10.0 if ctx.quick else 60.0
    site = f", {processes_wanted} daphne"
    reads = result.new_series(f"API reads (GET nodes, node, robots, gateways, transitions, logs){site}")
    moves = result.new_series(f"API transitions (10 nodes, one each per second){site}")
    lag = result.new_series(f"load generator's lag behind its schedule{site}")
    shown = result.new_series(f"transition requested -> new state on its node page{site}")
    with ctx.stack(f"{NAME}-{processes_wanted}", [(ROBOT, DOMAIN)],
                   LIFECYCLE_WEB_PROCESSES=str(processes_wanted)) as stack:
        stack.start_robot("robot", DOMAIN, generic=NODES, prefix="load_node")
        keys = [f"{ROBOT}.load_node_{i:03d}" for i in range(NODES)]
        stack.wait_nodes(keys, 90, state="unconfigured")
        robot = stack.children[-1]
        processes = {"daphne": stack.site, "gateway": stack.gateway, "ingest": stack.ingest}
        rss_before = {name: tree_rss_mb(child.pid) for name, child in processes.items()}
        busy = {**processes, "robot process": robot}
        cpu_before = {name: tree_cpu_seconds(child.pid) for name, child in busy.items()}
        tally, sockets = Tally(), Sockets()

        async def measure() -> None:
            stop_sockets, ready = asyncio.Event(), asyncio.Event()
            paths = [("/ws/fleet/", None) if i % 2 == 0 else (f"/ws/nodes/{keys[(i // 2) % NODES]}/",
                                                               keys[(i // 2) % NODES]) for i in range(SOCKETS)]
            watchers = [asyncio.create_task(watch(stack, path, key, sockets, ready, stop_sockets, SOCKETS))
                        for path, key in paths]
            await asyncio.wait_for(ready.wait(), 60)
            await asyncio.sleep(1.0)  # the snapshots on connect are not pushes
            stop_load = threading.Event()
            read_rate = (REQUESTS_PER_S - TRANSITIONS_PER_S) / READERS
            start = time.monotonic() + 0.2  # every client's schedule counts from here
            threads = [threading.Thread(target=reader, args=(stack, read_paths(keys), read_rate, seconds, stop_load,
                                                             reads, lag, tally, start, phase))
                       for phase in phases(READERS, read_rate)]
            # The transitions fall between the reads' slots (half a read slot later).
            shift = 0.5 / (READERS * read_rate)
            threads += [threading.Thread(target=operator, args=(stack, key, seconds, stop_load, moves, lag, tally,
                                                                start, shift + phase))
                        for key, phase in zip(keys, phases(NODES, TRANSITIONS_PER_S / NODES), strict=True)]
            began, cpu_began = time.monotonic(), time.process_time()
            cpu_before.update({name: tree_cpu_seconds(child.pid) for name, child in busy.items()})
            for thread in threads:
                thread.start()
            try:
                while any(t.is_alive() for t in threads):
                    await asyncio.sleep(0.2)
            finally:
                stop_load.set()
                for thread in threads:
                    thread.join(30)
                lasted = time.monotonic() - began
                result.figure(f"load phase lasted{site}", lasted, "s")
                # The generator shares the machine: if it is busy itself, its clients' latencies grow too.
                result.figure(f"load generator's own CPU (of one core){site}",
                              100 * (time.process_time() - cpu_began) / lasted, "%")
                for name, child in busy.items():
                    share = 100 * (tree_cpu_seconds(child.pid) - cpu_before[name]) / lasted
                    result.figure(f"{name} CPU during the load (of one core){site}", share, "%")
            await asyncio.sleep(1.0)  # the last pushes
            still_open = sum(1 for w in watchers if not w.done())
            stop_sockets.set()
            await asyncio.gather(*watchers, return_exceptions=True)
            result.figure(f"sockets open at the end{site}", still_open)

        with profiled(ctx, stack, f"{NAME}-{processes_wanted}"):
            asyncio.run(measure())
        rss_after = {name: tree_rss_mb(child.pid) for name, child in processes.items()}
    never = show_latencies(tally.requested, sockets.shown, shown)
    sent = len(reads.values) + len(moves.values)
    lasted = result.figures[f"load phase lasted{site}"][0]
    result.figure(f"API requests answered{site}", sent)
    result.figure(f"API requests per second (achieved){site}", sent / lasted, "/s")
    result.figure(f"API errors (non-2xx or failed connection){site}", len(tally.errors))
    result.figure(f"WebSocket clients connected{site}", sockets.opened)
    result.figure(f"WebSocket clients dropped before the end{site}", len(sockets.dropped))
    result.figure(f"WebSocket messages received{site}", sockets.messages)
    result.figure(f"transitions never shown on their node page{site}", never)
    for name in processes:
        result.figure(f"{name} memory before -> after{site}", rss_after[name] - rss_before[name], "MB growth")
        result.figure(f"{name} memory after{site}", rss_after[name], "MB")
    result.notes.extend(tally.errors[:10])
    result.notes.extend(sockets.dropped[:10])
    api_p99 = percentile(reads.values + moves.values, 99)
    shown_p99 = percentile(shown.values, 99) if shown.values else float("inf")
    result.check(f"API errors{site}", len(tally.errors), "= 0", not tally.errors)
    result.check(f"sockets dropped{site}", len(sockets.dropped), "= 0",
                 not sockets.dropped and sockets.opened == SOCKETS)
    result.check(f"API p99 (all requests){site}", api_p99, f"< {API_P99_TARGET_MS:g}", api_p99 < API_P99_TARGET_MS,
                 "ms")
    result.check(f"requested -> shown p99{site}", shown_p99, f"< {SHOWN_P99_TARGET_MS:g}",
                 shown_p99 < SHOWN_P99_TARGET_MS and not never, "ms")
