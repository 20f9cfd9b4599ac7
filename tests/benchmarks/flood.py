"""Scenario 4: one node logs as fast as it can for 10 s.

Counts the records along the way: sent by the node, received by the gateway, dropped by its
bounded buffer, handed to its outbox (batches for the Redis logs stream), stored in the
database by the ingest process (counted in the database), relayed to a WebSocket client of
the node's log console (``ws/logs/node/<id>/``; the ingest process pushes records after it
stored them). Meanwhile the fleet page is fetched every quarter second, the resident memory
of gateway, site and ingest sampled, and the logs stream's backlog in Redis read.
"""
from __future__ import annotations

import asyncio
import json
import threading
import time

from tests.benchmarks.harness import BenchContext, Stack
from tests.benchmarks.probe import LineProcess
from tests.benchmarks.processes import BenchError
from tests.benchmarks.profiling import profiled
from tests.benchmarks.report import ScenarioResult, Series
from tests.benchmarks.system import loadavg, rss_mb
from tests.benchmarks.web import Http, received, ws_connect

NAME = "flood"
TITLE = "4. Log flood: one node logging as fast as it can"
DOMAIN = 122
ROBOT = "bench-flood"
NODE = "log_flooder"
DRAIN_TIMEOUT_S = 90.0
STABLE_S = 2.0
# "Memory flat": once the gateway's bounded buffer is full (it starts dropping), the gateway
# grows by at most this much until the flood ends; if it never fills, over the second half.
FLAT_MB = 5.0


class Relayed:
    """Records reaching the log console's WebSocket."""

    def __init__(self) -> None:
        self.records = 0
        self.last = 0.0


async def count_records(web: Http, key: str, relayed: Relayed, ready: asyncio.Event, stop: asyncio.Event) -> None:
    async with ws_connect(web, f"/ws/logs/node/{key}/") as ws:
        ready.set()
        async for arrived, message in received(ws, stop):
            records = json.loads(message).get("records", [])
            if records:
                relayed.records += len(records)
                relayed.last = arrived


# (monotonic time, gateway RSS MB, site RSS MB, ingest RSS MB, dropped so far, Redis backlog in batches)
Sample = tuple[float, float, float, float, int, int]
PROCESSES = ("gateway", "site", "ingest")


def memory_of(stack: Stack) -> tuple[float, float, float]:
    return rss_mb(stack.gateway.pid), rss_mb(stack.site.pid), rss_mb(stack.ingest.pid)


def observe(stack: Stack, web: Http, pages: Series, memory: list[Sample], stop: threading.Event) -> None:
    """Fetch the fleet page, sample memory and the backlog until told to stop (a thread of its own)."""
    while not stop.is_set():
        response = web.get("/")
        if response.status == 200:
            pages.add(response.ms)
        dropped = stack.gateway_stats().get("logs_dropped", 0)
        memory.append((time.monotonic(), *memory_of(stack), dropped, stack.stream_backlog("logs")))
        stop.wait(0.25)


def wait_drained(stack: Stack, relayed: Relayed) -> tuple[dict, dict, float]:
    """Until the stored count (database) and the relayed count stop moving, with nothing left
    in the gateway's buffer and outbox or in the Redis stream."""
    deadline = time.monotonic() + DRAIN_TIMEOUT_S
    last_seen, last_change = (-1, -1), time.monotonic()
    gateway: dict = {}
    ingest: dict = {}
    while time.monotonic() < deadline:
        gateway, ingest = stack.gateway_stats(), stack.ingest_stats()
        seen = (ingest.get("logs_stored", 0), relayed.records)
        if seen != last_seen:
            last_seen, last_change = seen, time.monotonic()
        elif (time.monotonic() - last_change > STABLE_S and not gateway.get("logs_buffered")
              and not gateway.get("outbox", {}).get("log_batches") and not stack.stream_backlog("logs")):
            return gateway, ingest, last_change
        time.sleep(0.1)
    raise BenchError(f"records were still on their way {DRAIN_TIMEOUT_S:g} s after the flood: gateway {gateway}, "
                     f"ingest {ingest}, Redis backlog {stack.stream_backlog('logs')} batches")


async def measure(stack: Stack, flooder: LineProcess, seconds: float, result: ScenarioResult) -> dict:
    key = f"{ROBOT}.{NODE}"
    relayed, ready, stop = Relayed(), asyncio.Event(), asyncio.Event()
    listener = asyncio.create_task(count_records(stack.web, key, relayed, ready, stop))
    await asyncio.wait_for(ready.wait(), 15)
    await asyncio.sleep(1.0)
    before, stored_before = stack.gateway_stats(), stack.ingest_stats()
    memory_before = memory_of(stack)
    pages = result.new_series("GET / fleet page during the flood")
    memory: list[Sample] = []
    done = threading.Event()
    observer_web = Http(stack.web.host, stack.web.port)
    observer_web.cookies = dict(stack.web.cookies)
    observer = threading.Thread(target=observe, args=(stack, observer_web, pages, memory, done), daemon=True)
    observer.start()
    began = time.monotonic()
    sent = await asyncio.to_thread(flooder.call, "flood", seconds + 30, seconds=seconds)
    after, stored_after, stored_done = await asyncio.to_thread(wait_drained, stack, relayed)
    done.set()
    observer.join(5)
    stop.set()
    await listener
    await asyncio.sleep(3.0)
    return {
        "sent": sent, "before": before, "after": after, "began": began, "stored_done": stored_done,
        "stored_before": stored_before, "stored_after": stored_after,
        "relayed": relayed, "memory_before": memory_before, "memory": memory, "memory_after": memory_of(stack),
    }


def report(run: dict, result: ScenarioResult) -> None:
    before, after, sent = run["before"], run["after"], run["sent"]

    def delta(name: str) -> int:
        return after.get(name, 0) - before.get(name, 0)

    def stored_delta(name: str) -> int:
        return run["stored_after"].get(name, 0) - run["stored_before"].get(name, 0)

    flood_s = sent["seconds"]
    received, dropped, collected = delta("logs_received"), delta("logs_dropped"), delta("logs_collected")
    stored = stored_delta("logs_stored")
    relayed: Relayed = run["relayed"]
    stored_s = max(run["stored_done"] - run["began"], flood_s)
    relayed_s = max(relayed.last - run["began"], flood_s)
    relay_rate = relayed.records / relayed_s
    result.figure("sent by the node", sent["sent"], "records")
    result.figure("sent per second", sent["sent"] / flood_s, "/s")
    result.figure("received by the gateway", received, "records")
    result.figure("lost before the gateway (DDS, sent - received)", sent["sent"] - received, "records")
    result.figure("dropped by the gateway's bounded buffer", dropped, "records")
    result.figure("sent by the gateway to its Redis logs stream", collected, "records")
    result.figure("stored in the database (ingest process)", stored, "records")
    result.figure("relayed to the WebSocket client (pushed by ingest)", relayed.records, "records")
    result.figure("stored but not relayed (lost on the way to the console)", stored - relayed.records, "records")
    result.figure("received per second (over the flood)", received / flood_s, "/s")
    result.figure("stored per second (until storing ended)", stored / stored_s, "/s")
    result.figure("relayed per second (until relaying ended)", relay_rate, "/s")
    result.figure("storing/relaying went on after the flood", max(stored_s, relayed_s) - flood_s, "s")
    result.figure("Redis logs stream backlog, peak", max((m[5] for m in run["memory"]), default=0),
                  "batches of <= 200")
    result.figure("log batches trimmed from Redis before ingest read them", stored_delta("logs_lost"), "batches")
    result.figure("gateway outbox: log batches dropped (Redis away)", after.get("outbox", {}).get("logs_dropped", 0),
                  "batches")
    ended = run["began"] + flood_s
    full_at = next((m[0] for m in run["memory"] if m[4] > before.get("logs_dropped", 0)), None)
    for i, process in enumerate(PROCESSES):
        result.figure(f"{process} RSS before the flood", run["memory_before"][i], "MB")
        result.figure(f"{process} RSS peak", max((m[1 + i] for m in run["memory"]), default=float("nan")), "MB")
        result.figure(f"{process} RSS after draining", run["memory_after"][i], "MB")
    gw_before, gw_after = run["memory_before"][0], run["memory_after"][0]
    result.check("relayed per second", relay_rate, ">= 5000 /s", relay_rate >= 5000, "/s")
    # Not a target of issue 6, but the log console promises every stored record (the records
    # all belong to the flooding node, whose console the client shows).
    result.check("stored records relayed", relayed.records / stored * 100 if stored else float("nan"), "100 %",
                 stored > 0 and relayed.records == stored, "%")
    result.figure("gateway RSS growth, before -> after", gw_after - gw_before, "MB")
    result.figure("ingest RSS growth, before -> after", run["memory_after"][2] - run["memory_before"][2], "MB")
    if full_at is not None:
        result.figure("buffer full (first drop) after the flood began", full_at - run["began"], "s")
    since = full_at if full_at is not None and full_at < ended else run["began"] + flood_s / 2
    window = [m[1] for m in run["memory"] if since <= m[0] <= ended]
    growth = max(window) - window[0] if window else float("nan")
    what = "once the buffer was full" if full_at is not None and full_at < ended else "in the 2nd half"
    result.check(f"gateway RSS growth {what}", growth, f"<= {FLAT_MB:g} MB", growth <= FLAT_MB, "MB")
    pages = next(s for s in result.series if s.name.startswith("GET /"))
    p95 = pages.summary()["p95"]
    result.check("fleet page during flood, p95", p95, "< 500 ms", p95 < 500, "ms")


def run(ctx: BenchContext) -> ScenarioResult:
    result = ScenarioResult(NAME, TITLE, load_before=loadavg())
    seconds = 6.0 if ctx.quick else 10.0  # the buffer fills within ~4 s at today's rates
    with ctx.stack(NAME, [(ROBOT, DOMAIN)]) as stack:
        flooder = LineProcess(stack, "flooder", "tests.benchmarks.flooder", str(DOMAIN), NODE)
        # A few other nodes on the robot, so the fleet page is not empty.
        stack.start_robot("robot", DOMAIN, generic=10, prefix="quiet")
        stack.wait_nodes([f"{ROBOT}.{NODE}"], 60, state="unconfigured")
        with profiled(ctx, stack, NAME):
            outcome = asyncio.run(measure(stack, flooder, seconds, result))
        flooder.close()
    report(outcome, result)
    return result
