"""Scenario 5 (on request: ``--only quiet``): live-update sockets on a quiet fleet stay open.

Fleet and node pages keep a WebSocket open for hours while nothing changes. Each of them
waits on the channel layer, whose Redis client blocks in BZPOPMIN for 5 s at a time; a client
read timeout that is not longer than that blocking pop kills a consumer every few seconds
(daphne closes its socket with 1011). Here ten fleet sockets and one socket per node of a
robot whose nodes stay idle are held open for ten minutes (one with ``--quick``), and every
close is counted with its code. ``hold_sockets`` is also what the browser test uses.
"""
from __future__ import annotations

import asyncio
import time
from collections import Counter
from dataclasses import dataclass

from websockets.exceptions import ConnectionClosed

from tests.benchmarks.harness import BenchContext
from tests.benchmarks.processes import wait_for
from tests.benchmarks.report import ScenarioResult
from tests.benchmarks.system import loadavg
from tests.benchmarks.web import Http, ws_connect

NAME = "quiet"
TITLE = "5. Quiet fleet: live-update WebSockets held open, none may close"
DOMAIN = 126
ROBOT = "bench-quiet"
NODES = 4
FLEET_SOCKETS = 10
SETTLE_S = 2.0  # what a socket gets on connect (snapshot, gateway banner) arrives within this


@dataclass
class SocketOutcome:
    """What happened to one socket while it was held open."""

    path: str
    messages_after_settle: int = 0
    close_code: int | None = None  # None: still open when the window ended
    close_reason: str = ""
    closed_after_s: float | None = None


async def _hold_one(web: Http, path: str, seconds: float, all_open: asyncio.Barrier) -> SocketOutcome:
    outcome = SocketOutcome(path)
    async with ws_connect(web, path) as ws:
        await asyncio.wait_for(all_open.wait(), 60)  # the window starts when every socket is open
        began = time.monotonic()
        settled, ends = began + SETTLE_S, began + seconds
        try:
            while (left := ends - time.monotonic()) > 0:
                try:
                    await asyncio.wait_for(ws.recv(), left)  # recv() may be cancelled safely
                except asyncio.TimeoutError:
                    break
                if time.monotonic() > settled:
                    outcome.messages_after_settle += 1
        except ConnectionClosed as closed:
            frame = closed.rcvd
            outcome.close_code = frame.code if frame is not None else 1006  # 1006: no close frame
            outcome.close_reason = frame.reason if frame is not None else ""
            outcome.closed_after_s = time.monotonic() - began
    return outcome


async def hold_sockets(web: Http, paths: list[str], seconds: float) -> list[SocketOutcome]:
    """Open a WebSocket per path with ``web``'s session, hold all open ``seconds``, report each."""
    all_open = asyncio.Barrier(len(paths))
    return list(await asyncio.gather(*(_hold_one(web, path, seconds, all_open) for path in paths)))


def summary(outcomes: list[SocketOutcome]) -> str:
    """One line for an assertion message or a note: how many closed, with which codes, when."""
    closed = [o for o in outcomes if o.close_code is not None]
    codes = Counter(o.close_code for o in closed)
    detail = ", ".join(f"{o.path} with {o.close_code} after {o.closed_after_s:.1f} s" for o in closed)
    return (f"{len(closed)} of {len(outcomes)} sockets closed"
            + (f" (codes {dict(codes)}): {detail}" if closed else ""))


def run(ctx: BenchContext) -> ScenarioResult:
    result = ScenarioResult(NAME, TITLE, load_before=loadavg())
    seconds = 60.0 if ctx.quick else 600.0
    keys = [f"{ROBOT}.quiet_node_{i:03d}" for i in range(NODES)]
    paths = ["/ws/fleet/"] * FLEET_SOCKETS + [f"/ws/nodes/{key}/" for key in keys]
    with ctx.stack(NAME, [(ROBOT, DOMAIN)]) as stack:
        stack.start_robot("robot", DOMAIN, generic=NODES, prefix="quiet_node")
        stack.wait_nodes(keys, 60, state="unconfigured")
        # The fleet page's gateway header shows the node count the ingest process copies from
        # the gateway's beat (every 2 s each): once it is right, nothing is left to change.
        wait_for(lambda: stack.ingest_stats().get("node_count") == NODES, 30, "the gateway's node count", 0.25)
        print(f"quiet: holding {len(paths)} sockets open for {seconds:.0f} s", flush=True)
        outcomes = asyncio.run(hold_sockets(stack.web, paths, seconds))
        daphne_log = stack.site.output() if stack.site else ""
    closed = [o for o in outcomes if o.close_code is not None]
    result.figure("window", seconds, "s")
    result.figure("sockets opened (fleet + node pages)", len(outcomes))
    result.figure("messages after the snapshot (quiet: 0)", sum(o.messages_after_settle for o in outcomes))
    for code, count in sorted(Counter(o.close_code for o in closed).items()):
        result.figure(f"sockets closed with code {code}", count)
    result.figure("'Timeout reading from' in daphne's log", daphne_log.count("Timeout reading from"))
    result.check("sockets closed during the window", len(closed), "0", not closed)
    if closed:
        result.notes.append(summary(outcomes))
    return result
