"""Scenario 13: diagnostics at fleet size. 10 robots (ROS domain 131, namespaces /bd0 ... /bd9) with
one DiagnosticArray publisher process each (tests/integration/diagnostics_publisher.py, 100 statuses,
as a robot's nodes publish /diagnostics, a key/value of each changing with every message as a
measured frequency does), first at 1 Hz, the usual rate, then at 10 Hz.

At each rate, once settled, with one robot's diagnostics page open (its WebSocket):
1. a steady window: the CPU of the gateway and of the site (the ingest process plus daphne), in %
   of one core, and what reached the site: facts per second (the gateway's facts stream in Redis:
   entries added), the statuses in them (sent when they changed: none while nothing changes) and
   the names of statuses heard again unchanged (read beside the ingest process as they are added;
   with key/values changing with every message, none: each status is sent every refresh, 2 s);
2. status change -> page: one status of robot 0 changed (level and a message text of its own) by its
   publisher, from the wall time of the first publication carrying it to the page's socket message
   containing that text, repeated with a pause between changes; split where the gateway added the
   fact carrying it to Redis (the entry's id is Redis's clock, this machine's).
"""
from __future__ import annotations

import asyncio
import json
import random
import re
import threading
import time

from tests.benchmarks.harness import BenchContext, Stack
from tests.benchmarks.processes import CHANNEL_PREFIX, run_manage, wait_for
from tests.benchmarks.profiling import profiled
from tests.benchmarks.report import ScenarioResult, Series
from tests.benchmarks.system import loadavg, tree_cpu_seconds
from tests.benchmarks.web import received, ws_connect
from tests.integration.diagnostics_publisher import Source

NAME = "diagnostics"
TITLE = "13. Diagnostics: 10 robots x 100 statuses at 1 and 10 Hz; CPU, status change -> page"
DOMAIN = 131
ROBOTS = [(f"bench-diag-{i}", DOMAIN) for i in range(10)]
NAMESPACES = {robot: f"/bd{i}" for i, (robot, _) in enumerate(ROBOTS)}
STATUSES = 100
RATES_HZ = (1.0, 10.0)
PAGE_ROBOT = ROBOTS[0][0]
CHANGED = "diag_source: check 7"  # the status changed on robot 0 (the publisher's own naming)
P99_TARGET_MS = 200.0
SHOWN_TIMEOUT_S = 5.0  # a change not on the page this long after its publication counts as never shown


class Sizes:
    def __init__(self, quick: bool) -> None:
        self.window_s = 8.0 if quick else 25.0
        self.rest_s = 3.0 if quick else 5.0
        self.settle_s = 3.0 if quick else 5.0
        self.changes = 12 if quick else 50
        self.pause_s = (0.3, 0.5)  # between one change's publication and the next order


class Publisher(Source):
    """The publisher process; stopped again if it does not come up (Source leaves it running)."""

    def __init__(self, domain: int, env: dict[str, str], *args: str) -> None:
        try:
            super().__init__(domain, env, *args)
        except BaseException:
            if getattr(self, "popen", None) is not None:
                self.stop()
            raise


def set_namespaces(stack: Stack) -> None:
    """The stack registers its robots by domain only; each is narrowed to its namespace, as an
    operator does with ``add_robot --namespace`` (one Django start for all ten)."""
    commands = [f"call_command('add_robot', {robot!r}, domain={domain}, namespace={NAMESPACES[robot]!r}, "
                f"gateway={stack.gateway_name!r})" for robot, domain in ROBOTS]
    run_manage(stack.env, "shell", "-c", "from django.core.management import call_command\n" + "\n".join(commands))


def start_publishers(stack: Stack, sources: list[Source]) -> None:
    """One publisher per robot, one after the other, each added to ``sources`` (which the caller
    stops, whatever happens) once it publishes."""
    for robot, _ in ROBOTS:
        sources.append(Publisher(DOMAIN, stack.env, "--namespace", NAMESPACES[robot], "--statuses", str(STATUSES),
                                 "--rate", f"{RATES_HZ[0]:g}", "--churn"))


def wait_statuses(stack: Stack, timeout: float) -> float:
    """Until the API lists every robot's statuses; seconds it took."""
    began = time.monotonic()

    def complete() -> bool:
        for robot, _ in ROBOTS:
            answer = stack.api.get(f"/api/v1/robots/{robot}/diagnostics")
            if answer.status != 200 or sum(answer.json()["counts"].values()) < STATUSES:
                return False
        return True

    wait_for(complete, timeout, f"{len(ROBOTS)} x {STATUSES} statuses listed by the API", 0.5)
    return time.monotonic() - began


class FactCounter:
    """Reads the gateway's facts stream beside the ingest process (no consumer group: what it reads
    stays for the ingest), counting diagnostics facts, the statuses they carry and the names of
    statuses heard again, and when each message text of the page's robot first came in a fact;
    ``entries-added`` of the stream counts every fact the gateway sent."""

    def __init__(self, stack: Stack) -> None:
        import redis

        from ros_gateway.shared import protocol

        self.redis = redis.Redis(host="127.0.0.1", port=stack.redis_port, socket_timeout=5)
        self.key = protocol.gateway_key(CHANNEL_PREFIX, stack.gateway_name, "facts")
        self.kind = protocol.DIAGNOSTICS
        self.facts = self.statuses = self.heard = self.read = 0
        self.seen: dict[str, float] = {}  # a message text of the page's robot -> when its fact was added
        self.stop = threading.Event()
        info = self.redis.xinfo_stream(self.key)
        self.added_before = int(info["entries-added"])
        self.thread = threading.Thread(target=self._run, args=(info["last-generated-id"],), daemon=True)
        self.thread.start()

    def _added(self) -> int:
        return int(self.redis.xinfo_stream(self.key)["entries-added"])

    def _run(self, last: bytes) -> None:
        while not self.stop.is_set():
            found = self.redis.xread({self.key: last}, block=200, count=1000)
            for _stream, entries in found or []:
                for entry_id, fields in entries:
                    last = entry_id
                    self.read += 1
                    fact = json.loads(fields[b"f"])
                    if fact.get("type") == self.kind:
                        self.facts += 1
                        self.statuses += len(fact.get("statuses") or [])
                        self.heard += len(fact.get("heard") or [])
                        if fact.get("robot") == PAGE_ROBOT:
                            added = int(entry_id.split(b"-")[0]) / 1000  # Redis's clock: this machine's
                            for status in fact.get("statuses") or []:
                                self.seen.setdefault(status.get("message"), added)

    def finish(self) -> int:
        """Stop reading; every fact the gateway added since the start."""
        self.stop.set()
        self.thread.join(5)
        added = self._added() - self.added_before
        self.redis.close()
        return added


class Window:
    """CPU seconds of the measured processes and the benchmark's own, from its start."""

    def __init__(self, stack: Stack, sources: list[Source]) -> None:
        self.pids = {"gateway": [stack.gateway.pid], "site (ingest + daphne)": [stack.ingest.pid, stack.site.pid],
                     "Redis": [stack.redis.pid], f"{len(sources)} publishers together": [s.popen.pid for s in sources]}
        self.before = self._read()
        self.began, self.own = time.monotonic(), time.process_time()

    def _read(self) -> dict[str, float]:
        return {name: sum(tree_cpu_seconds(pid) for pid in pids) for name, pids in self.pids.items()}

    def shares(self) -> tuple[float, dict[str, float]]:
        """Seconds since the start, and % of one core per process (group) since."""
        lasted = time.monotonic() - self.began
        now = self._read()
        shares = {name: 100 * (now[name] - self.before[name]) / lasted for name in now}
        shares["benchmark process itself"] = 100 * (time.process_time() - self.own) / lasted
        return lasted, shares


async def page_phase(stack: Stack, sources: list[Source], sizes: Sizes, label: str, result: ScenarioResult
                     ) -> tuple[Series, int]:
    """With robot 0's diagnostics page open: the steady window (CPU, facts), then the changes. The
    series of milliseconds from each change's publication to the page's message showing it (and its
    two parts, split where the gateway added the fact to Redis); the changes never shown."""
    arrivals: list[tuple[float, str]] = []  # wall time, text
    stop, ready = asyncio.Event(), asyncio.Event()

    async def listen() -> None:
        async with ws_connect(stack.web, f"/ws/robots/{PAGE_ROBOT}/diagnostics/") as ws:
            ready.set()
            async for arrived, message in received(ws, stop):
                if isinstance(message, str):
                    arrivals.append((arrived + time.time() - time.monotonic(), message))

    task = asyncio.create_task(listen())
    try:
        await asyncio.wait_for(ready.wait(), 15)
        await asyncio.sleep(1.5)  # the page's first draw is no update

        # 1. Steady window.
        arrivals.clear()
        window, counter = Window(stack, sources), FactCounter(stack)
        await asyncio.sleep(sizes.window_s)
        lasted, shares = window.shares()
        added = await asyncio.to_thread(counter.finish)
        backlog = await asyncio.to_thread(stack.stream_backlog, "facts")
        for name, share in shares.items():
            result.figure(f"{label}: {name} CPU", share, "% of a core")
        result.figure(f"{label}: load average at the window's end", loadavg()[0], "")
        result.figure(f"{label}: facts reaching the site", added / lasted, "/s")
        result.figure(f"{label}: statuses sent in diagnostics facts", counter.statuses / lasted, "/s")
        result.figure(f"{label}: names heard again (unchanged) in them", counter.heard / lasted, "/s")
        if counter.read < added:
            result.notes.append(f"{label}: the stream reader saw {counter.read} of {added} facts (the rest stored "
                                "and trimmed by the ingest process first)")
        result.figure(f"{label}: facts not yet stored at the window's end", backlog, "")
        result.figure(f"{label}: page messages during the window (no change made)", len(arrivals) / lasted, "/s")

        # 2. Status change -> page; where the time goes: until the gateway added its fact to Redis.
        sent: list[tuple[float, str]] = []
        tracer = FactCounter(stack)
        source = sources[0]
        for i in range(sizes.changes):
            text = f"{label.replace(' ', '')}-change-{i:04d}"
            published = await asyncio.to_thread(source.send, name=CHANGED, level=1 + i % 2, message=text,
                                                values=[["index", "7"]])
            sent.append((published, text))
            await asyncio.sleep(random.uniform(*sizes.pause_s))
        await asyncio.sleep(SHOWN_TIMEOUT_S)
        await asyncio.to_thread(source.send, name=CHANGED, level=0, message="fine", values=[["index", "7"]])
        await asyncio.to_thread(tracer.finish)
    finally:
        stop.set()
        await asyncio.gather(task, return_exceptions=True)
    total = result.new_series(f"{label}: status change (publication) -> page shows it")
    gateway = result.new_series(f"{label}:   publication -> its fact added to Redis (gateway)")
    site = result.new_series(f"{label}:   fact added to Redis -> page shows it (ingest, daphne)")
    # The page shows the newest message of the status: a change drawn only together with the next one
    # is shown (superseded) when the next one is, and counted apart.
    tag = f"{label.replace(' ', '')}-change-"
    newest = [(at, max((int(n) for n in re.findall(re.escape(tag) + r"(\d{4})", message)), default=-1))
              for at, message in arrivals]
    never = superseded = 0
    for index, (published, text) in enumerate(sent):
        shown, which = next(((at, n) for at, n in newest if n >= index and at >= published), (None, -1))
        if shown is None or shown - published > SHOWN_TIMEOUT_S:
            never += 1
            where = "its fact reached Redis" if text in tracer.seen else "no fact carried it"
            result.notes.append(f"{label}: {text} not shown within {SHOWN_TIMEOUT_S:g} s ({where})")
            continue
        total.add((shown - published) * 1000)
        if which > index:
            superseded += 1
            continue
        added = tracer.seen.get(text)
        if added is not None:
            gateway.add((added - published) * 1000)
            site.add((shown - added) * 1000)
    result.figure(f"{label}: changes first shown together with the next (superseded)", superseded, "")
    return total, never


def at_rate(stack: Stack, sources: list[Source], sizes: Sizes, rate: float, ctx: BenchContext,
            result: ScenarioResult) -> None:
    label = f"{rate:g} Hz"
    for source in sources:
        source.send(rate=rate)
    time.sleep(sizes.settle_s)  # past a refresh period (2 s) at the new rate
    with profiled(ctx, stack, f"{NAME}-{rate:g}hz"):
        series, never = asyncio.run(page_phase(stack, sources, sizes, label, result))
    p99 = series.summary()["p99"]
    result.check(f"{label}: status change -> page, p99", p99, f"< {P99_TARGET_MS:g} ms",
                 p99 < P99_TARGET_MS and never == 0, "ms")
    result.figure(f"{label}: changes never shown within {SHOWN_TIMEOUT_S:g} s", never, "")


def run(ctx: BenchContext) -> ScenarioResult:
    result = ScenarioResult(NAME, TITLE, load_before=loadavg())
    sizes = Sizes(ctx.quick)
    with ctx.stack(NAME, ROBOTS) as stack:
        set_namespaces(stack)
        rest = Window(stack, [])
        time.sleep(sizes.rest_s)
        _, shares = rest.shares()
        result.figure("before any publisher: gateway CPU", shares["gateway"], "% of a core")
        result.figure("before any publisher: site (ingest + daphne) CPU", shares["site (ingest + daphne)"],
                      "% of a core")
        sources: list[Source] = []
        try:
            start_publishers(stack, sources)
            result.figure(f"publishers ready -> API lists all {len(ROBOTS) * STATUSES} statuses",
                          wait_statuses(stack, 60), "s")
            for rate in RATES_HZ:
                at_rate(stack, sources, sizes, rate, ctx, result)
        finally:
            for source in sources:
                source.stop()
    slow, fast = (f"{r:g} Hz" for r in RATES_HZ)
    for name in ("gateway", "site (ingest + daphne)"):
        before = result.figures[f"{slow}: {name} CPU"][0]
        if before > 0:
            result.figure(f"{name} CPU, {fast} / {slow}", result.figures[f"{fast}: {name} CPU"][0] / before, "x")
    result.notes.append(f"{len(ROBOTS)} robots x {STATUSES} statuses, one rclpy publisher process each (domain "
                        f"{DOMAIN}); the page is {PAGE_ROBOT}'s; changes: {CHANGED!r}, level WARN/ERROR in turn, "
                        "a message text of its own each time")
    if ctx.profile_dir is not None:
        result.notes.append("profiled: py-spy sampled gateway, daphne and ingest, so their CPU is higher than without")
    result.notes.append(json.dumps({"window_s": sizes.window_s, "changes": sizes.changes, "settle_s": sizes.settle_s}))
    return result
