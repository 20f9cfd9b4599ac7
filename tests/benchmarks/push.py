"""Scenario 2: from a node's ~/transition_event being published to the WebSocket message
that shows the new state reaching a logged-in client (the node page, and the fleet page).

Transitions are triggered from the benchmark's own rclpy process (ros_probe.py), which also
subscribes to the node's ~/transition_event and stamps each event on arrival with the
machine's monotonic clock; the WebSocket clients stamp each message with the same clock.
The probe's own arrival is after the publish, so the figures are, if anything, a fraction of
a millisecond too good; "request -> event at probe" bounds that error.

Beside the state, the node page gets an audit row for each of these (external) transitions
once it is stored: "end event -> audit row" is how long a fact takes to be written and shown
(the gateway's facts stream, the ingest process, the database, its push).
"""
from __future__ import annotations

import asyncio
import re
import time

from tests.benchmarks.harness import BenchContext, Stack
from tests.benchmarks.probe import RosProbe
from tests.benchmarks.processes import BenchError
from tests.benchmarks.profiling import profiled
from tests.benchmarks.report import ScenarioResult, Series
from tests.benchmarks.system import loadavg
from tests.benchmarks.web import Http, received, ws_connect

NAME = "push"
TITLE = "2. Push latency: transition_event published -> WebSocket message at the browser"
DOMAIN = 121
ROBOT = "bench-push"
NODE = "push_node_000"
CYCLE_IDS = [1, 3, 4, 2]  # configure, activate, deactivate, cleanup
PAUSE_S = 0.15
TRANSITION_STATES = {"configuring", "cleaningup", "shuttingdown", "activating", "deactivating", "errorprocessing"}
NODE_BADGE = re.compile(r'class="badge big state-([a-z]+)"')
ROW_BADGE = re.compile(r'class="badge state-([a-z]+)"')
AUDIT_ROW = re.compile(r"([a-z?]+) \u2192 ([a-z?]+)</td>")  # _audit_row.html: "from -> to"

Arrival = tuple[float, str]  # (monotonic time, state label shown)


async def listen(web: Http, path: str, badge: re.Pattern, must_contain: str, sink: list[Arrival],
                 ready: asyncio.Event, stop: asyncio.Event, audit: list[Arrival] | None = None) -> None:
    """Stamp each state update (and, with ``audit``, each new audit row: its result state)."""
    async with ws_connect(web, path) as ws:
        ready.set()
        async for arrived, message in received(ws, stop):
            if not isinstance(message, str):
                continue
            if must_contain in message:
                match = badge.search(message)
                if match:
                    sink.append((arrived, match.group(1)))
            if audit is not None and "#audit-rows" in message:
                row = AUDIT_ROW.search(message)
                if row:
                    audit.append((arrived, row.group(2)))


async def drive(stack: Stack, probe: RosProbe, fqn: str, key: str, count: int) -> tuple[list, list[float], dict]:
    """Trigger ``count`` transitions while both pages listen; returns events, send times, arrivals."""
    arrivals: dict[str, list[Arrival]] = {"node page": [], "fleet page": [], "audit rows": []}
    stop = asyncio.Event()
    readies = [asyncio.Event(), asyncio.Event()]
    row_id = "node-" + key.replace(".", "__")
    tasks = [
        asyncio.create_task(listen(stack.web, f"/ws/nodes/{key}/", NODE_BADGE, 'id="node-state"',
                                   arrivals["node page"], readies[0], stop, arrivals["audit rows"])),
        asyncio.create_task(listen(stack.web, "/ws/fleet/", ROW_BADGE, f'id="{row_id}"',
                                   arrivals["fleet page"], readies[1], stop)),
    ]
    await asyncio.wait_for(asyncio.gather(*(r.wait() for r in readies)), 15)
    await asyncio.sleep(1.0)  # the snapshots on connect are not pushes
    for sink in arrivals.values():
        sink.clear()
    await asyncio.to_thread(probe.call, "events")
    sent: list[float] = []
    for i in range(count):
        answer = await asyncio.to_thread(probe.change, fqn, CYCLE_IDS[i % len(CYCLE_IDS)])
        sent.append(answer["sent"])
        await asyncio.sleep(PAUSE_S)
    await asyncio.sleep(2.0)  # the last pushes (audit rows come after the ingest process stored them)
    stop.set()
    await asyncio.gather(*tasks)
    events = (await asyncio.to_thread(probe.call, "events"))["events"]
    return events, sent, arrivals


def match(events: list, arrivals: list[Arrival], begin: Series, end: Series, both: Series) -> int:
    """Pair each event with the first later message showing its goal state; returns misses."""
    missing, j = 0, 0
    for published, _start, goal in events:
        k = next((k for k in range(j, len(arrivals)) if arrivals[k][1] == goal), None)
        if k is None:
            missing += 1
            continue
        latency = (arrivals[k][0] - published) * 1000
        (begin if goal in TRANSITION_STATES else end).add(latency)
        both.add(latency)
        j = k + 1
    return missing


def run(ctx: BenchContext) -> ScenarioResult:
    result = ScenarioResult(NAME, TITLE, load_before=loadavg())
    count = 16 if ctx.quick else 80
    key, fqn = f"{ROBOT}.{NODE}", f"/{NODE}"
    with ctx.stack(NAME, [(ROBOT, DOMAIN)]) as stack:
        stack.start_robot("robot", DOMAIN, generic=1, prefix="push_node")
        stack.wait_nodes([key], 60, state="unconfigured")
        probe = RosProbe(stack, DOMAIN)
        probe.call("watch", node=fqn)
        probe.change(fqn, 1)  # warm-up cycle: clients matched, templates loaded
        for transition_id in CYCLE_IDS[1:]:
            probe.change(fqn, transition_id)
        time.sleep(0.5)
        with profiled(ctx, stack, NAME):
            events, sent, arrivals = asyncio.run(drive(stack, probe, fqn, key, count))
        probe.close()
    if len(events) < count:
        raise BenchError(f"the probe saw {len(events)} transition events for {count} transitions")
    for page in ("node page", "fleet page"):
        both = result.new_series(f"{page}: event -> WebSocket, all")
        begin = result.new_series(f"{page}:   begin events (-> ...ing)")
        end = result.new_series(f"{page}:   end events (-> primary state)")
        missing = match(events, arrivals[page], begin, end, both)
        result.figure(f"{page}: events without a matching push", missing)
        if page == "node page":
            result.check("node page push median", both.median, "< 20 ms", both.median < 20, "ms")
            p99 = both.summary()["p99"]
            result.check("node page push p99", p99, "< 100 ms", p99 < 100, "ms")
    audit = result.new_series("node page: end event -> audit row (stored, then pushed)")
    ends = [e for e in events if e[2] not in TRANSITION_STATES]
    missing = match(ends, arrivals["audit rows"], audit, audit, Series("all audit rows"))
    result.figure("node page: audit rows received", len(arrivals["audit rows"]))
    result.figure("node page: transitions without an audit row", missing)
    bound = result.new_series("probe: request sent -> begin event received")
    for t in sent:
        later = [e[0] for e in events if e[0] >= t]
        if later:
            bound.add((min(later) - t) * 1000)
    return result
