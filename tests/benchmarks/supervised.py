"""Scenario 11 (issue 28): the gateway as the supervisor of a robot's processes (launch profiles).

1. Restart -> every node of the process back in its desired state. A launch profile runs a demo
   robot process with 1 generic node, another one with 50; the robot recovers automatically and
   every node of the profile has the desired state ``active``. After a group bring-up, the
   process is restarted through the API (``POST /api/v1/robots/{name}/processes/{process}``)
   again and again; each time is measured from the request until the API lists every node of
   the profile as a new instance (its process ``restarted`` since the request), alive and active.
   The gateway recovers one node at most RECOVERY_LIMIT times within RECOVERY_WINDOW_S (its
   crash-loop guard, ros_gateway/groups.py): after that many restarts a profile is replaced by a
   fresh one with other node names (a "round").
2. The gateway at rest with 20 supervised processes: 20 profiles of one demo robot process with
   one generic node each (real ROS processes, all of them), all running and their nodes read;
   after a settle, the CPU of the gateway process itself (not its children: those are the
   supervised processes) over 30 s, and its resident memory; the same before any profile, and
   with 20 ``sleep`` processes instead (supervision alone: no node to watch).

At the end the profiles are deleted (the gateway stops their processes) and the stack stops;
no demo robot process of this scenario may be left. The profiles are written by the functions
of launch_profiles.py run through ``manage.py shell`` with the stack's settings (as timeline.py seeds its records).
"""
from __future__ import annotations

import contextlib
import json
import os
import signal
import sqlite3
import time
from datetime import datetime, timezone

from tests.benchmarks.bringup import group_run
from tests.benchmarks.harness import BenchContext, Stack
from tests.benchmarks.launch_profiles import (
    PREFIX,
    SLEEP_ARG,
    START_TIMEOUT_S,
    alive,
    demo_robot,
    in_site,
    processes,
    robot_args,
    sleeper,
    wait_gone,
    wait_running,
)
from tests.benchmarks.processes import PYTHON, BenchError, database_url, wait_for
from tests.benchmarks.profiling import profiled
from tests.benchmarks.report import ScenarioResult
from tests.benchmarks.system import cpu_seconds, loadavg, rss_mb, tree

NAME = "supervised"
TITLE = "11. Supervised processes: restart -> nodes back in their desired state; the gateway at rest with 20"
# Shared with the scale scenario; scenarios run one after the other.
ROBOT, DOMAIN = "bench-supervised", 123
REST_ROBOT, REST_DOMAIN = "bench-supervised-rest", 124
RECOVERY_LIMIT = 3  # ros_gateway.groups.RECOVERY_LIMIT: recoveries of one node within 300 s, at most
CONFIG_S = 3.0  # the gateway reads its config every 2 s: a desired state saved is known after this
RESTART_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 30.0
POLL_S = 0.1
EXECUTOR_DIED = "stopped"  # (after EXECUTOR_LINE) the gateway's log line when one died, before 2026-11-26
EXECUTOR_LINE = "an executor of ROS domain"  # ... "failed (N time(s) in 10 s); spinning on" since
REST_PROCESSES = 20
RESTART_TARGET_S = 3.0  # 50 nodes active again, median
REST_CPU_TARGET = 2.0  # % of one core


def moment(text: str | datetime | None) -> datetime | None:
    """An ISO time (or a database's datetime; SQLite's without a zone, which Django stores as UTC)."""
    if not text:
        return None
    at = text if isinstance(text, datetime) else datetime.fromisoformat(text)
    return at if at.tzinfo else at.replace(tzinfo=timezone.utc)


class Store:
    """Read-only queries on the stack's database, as Stack.ingest_stats reads it: the supervised
    processes' output is stored as log records (logger <profile>/stdout), with no API of its own."""

    def __init__(self, stack: Stack) -> None:
        url = database_url(stack.dir)
        if url.startswith("postgres"):
            import psycopg

            self.db, self.mark = psycopg.connect(url, autocommit=True), "%s"
        else:
            self.db, self.mark = sqlite3.connect(stack.db_path, timeout=10, isolation_level=None), "?"

    def close(self) -> None:
        self.db.close()

    def ready_at(self, profile: str) -> datetime | None:
        """When the gateway read the profile's last "demo robot ready" line (its nodes exist)."""
        row = self.db.execute(f"SELECT stamp FROM fleet_logrecord WHERE logger = {self.mark} AND message LIKE "
                              f"'demo robot ready%' ORDER BY id DESC LIMIT 1", (f"{profile}/stdout",)).fetchone()
        return moment(row[0]) if row else None


# -- 1. restart -> every node back in its desired state ------------------------------------------
class Restarts:
    """The series of one node count, and the rounds (fresh profiles) they took."""

    def __init__(self, result: ScenarioResult, count: int) -> None:
        self.what = what = f"{count} node{'s' if count > 1 else ''}"
        self.count = count
        self.answered = result.new_series(f"{what}: restart answered (old process stopped, new one started)", "s")
        self.ready = result.new_series(f"{what}: restart -> new process printed 'demo robot ready' (gateway clock)",
                                       "s")
        self.new = result.new_series(f"{what}: restart -> every node listed as a new instance", "s")
        self.recovered = result.new_series(f"{what}: restart -> last recovery step done (audit, gateway clock)", "s")
        self.back = result.new_series(f"{what}: restart -> every node listed alive and active again", "s")
        self.failures: list[str] = []
        self.unrecorded = 0  # nodes without a process_restarted or a recovery record after a restart


def set_up_round(stack: Stack, profile: str, count: int, prefix: str, pids: set[int]) -> tuple[list[str], list[str]]:
    """A fresh profile running ``count`` nodes, their desired state active, brought up once; their keys and names."""
    in_site(stack, f"add_profiles({ROBOT!r}, {[demo_robot(profile, DOMAIN, count, prefix)]!r})")
    wait_running(stack, ROBOT, [profile], pids)
    names = [f"/{prefix}_{i:03d}" for i in range(count)]
    keys = [f"{ROBOT}.{name.strip('/')}" for name in names]
    stack.wait_nodes(keys, START_TIMEOUT_S)
    saved = time.monotonic()
    wanted = int(in_site(stack, f"want_active({ROBOT!r}, {prefix!r})").strip().splitlines()[-1])
    if wanted != count:
        raise BenchError(f"desired state set on {wanted} nodes of {profile}, not {count}")
    group_run(stack, ROBOT, "bringup", names)
    stack.wait_nodes(keys, 30, state="active")
    time.sleep(max(0.0, CONFIG_S - (time.monotonic() - saved)))  # the gateway knows the desired states
    return keys, names


def one_restart(stack: Stack, store: Store, profile: str, keys: list[str], restarts: Restarts,
                pids: set[int]) -> None:
    """Restart the profile's process; wait until each node is a new instance, alive and active."""
    asked_at = datetime.now(timezone.utc)
    began = time.monotonic()
    answer = stack.api.post_json(f"/api/v1/robots/{ROBOT}/processes/{profile}", {"action": "restart"})
    if answer.status != 200:
        raise BenchError(f"restart of {profile} answered {answer.status}: {answer.body[:300]!r}")
    restarts.answered.add(answer.ms / 1000)
    record = answer.json()["record"]
    if record["pid"] is not None:
        pids.add(record["pid"])
    if record["pid"] in (None, record["old_pid"]):
        raise BenchError(f"restart of {profile}: no new pid in its record {record}")
    marks: dict[str, float] = {}
    listed: dict[str, dict] = {}
    deadline = began + RESTART_TIMEOUT_S
    while "back" not in marks:
        now = time.monotonic()
        if now > deadline:
            restarts.failures.append(f"{profile}: not all {len(keys)} nodes back within {RESTART_TIMEOUT_S:g} s: "
                                     f"{summary(listed, keys)}")
            return
        listed = {n["id"]: n for n in stack.nodes(ROBOT)}
        fresh = [listed.get(k) for k in keys]
        fresh = [n for n in fresh if n and n["process"]["status"] == "restarted"
                 and (moment(n["process"]["since"]) or asked_at) > asked_at]
        if len(fresh) == len(keys):
            marks.setdefault("new", now)
            if all(n["alive"] and n["state"]["label"] == "active" for n in fresh):
                marks["back"] = now
        time.sleep(POLL_S)
    restarts.new.add(marks["new"] - began)
    restarts.back.add(marks["back"] - began)
    done = recovery_records(stack, keys, asked_at, restarts)
    if done is not None:
        restarts.recovered.add((done - asked_at).total_seconds())
    # Its output line is stored on another path (the logs stream): it may come a moment later.
    try:
        ready = wait_for(lambda: (at := store.ready_at(profile)) and at > asked_at and at, 10,
                         f"{profile}'s 'demo robot ready' line in the log records", 0.1)
        restarts.ready.add((ready - asked_at).total_seconds())
    except BenchError as exc:
        restarts.failures.append(f"{profile}: {exc}")


def summary(listed: dict[str, dict], keys: list[str]) -> str:
    """How the profile's nodes are listed: counts of (alive, state, process status)."""
    counts: dict[str, int] = {}
    for key in keys:
        node = listed.get(key)
        what = "not listed" if node is None else (
            f"{'alive' if node['alive'] else 'gone'} {node['state']['label']} process={node['process']['status']}")
        counts[what] = counts.get(what, 0) + 1
    return json.dumps(counts)


def recovery_records(stack: Stack, keys: list[str], asked_at: datetime, restarts: Restarts) -> datetime | None:
    """Each node's audit records since the restart: its new instance (process_restarted) and its
    recovery to active; the last recovery step's completion (None if a node has none)."""
    answer = stack.api.get(f"/api/v1/transitions?robot={ROBOT}&limit=1000")
    if answer.status != 200:
        raise BenchError(f"GET transitions answered {answer.status}: {answer.body[:300]!r}")
    since = [r for r in answer.json()["transitions"] if moment(r["requested_at"]) >= asked_at]
    restarted = {r["node_id"] for r in since if r["outcome"] == "process_restarted"}
    recovered = {r["node_id"]: moment(r["completed_at"]) for r in since if r["source"] == "recovery"
                 and r["outcome"] == "succeeded" and (r["to"] or {}).get("label") == "active"}
    missing = [k for k in keys if k not in restarted or recovered.get(k) is None]
    restarts.unrecorded += len(missing)
    return None if missing else max(recovered[k] for k in keys)


def end_round(stack: Stack, robot: str, pids: set[int]) -> float:
    """Delete the robot's profiles and wait until their processes have ended; how long that took."""
    running = [process["pid"] for process in processes(stack, robot).values() if process.get("pid")]
    began = time.monotonic()
    in_site(stack, f"remove_profiles({robot!r})")
    wait_for(lambda: not any(alive(pid) for pid in running), STOP_TIMEOUT_S,
             f"the gateway to stop {len(running)} processes of {robot}", 0.1)
    return time.monotonic() - began


def measure_restarts(stack: Stack, store: Store, count: int, samples: int, result: ScenarioResult,
                     pids: set[int]) -> Restarts:
    """``samples`` restarts, in rounds of RECOVERY_LIMIT; a round that cannot be set up, or a
    gateway whose executor died (its nodes would not answer any more), ends the measurement."""
    restarts = Restarts(result, count)
    round_ = 0
    while len(restarts.answered.values) < samples and not executors_stopped(stack):
        take = min(RECOVERY_LIMIT, samples - len(restarts.answered.values))
        profile, prefix = f"nodes{count}-r{round_}", f"{PREFIX}{count}r{round_}"
        round_ += 1
        try:
            keys, _ = set_up_round(stack, profile, count, prefix, pids)
            for _ in range(take):
                one_restart(stack, store, profile, keys, restarts, pids)
        except BenchError as exc:
            restarts.failures.append(f"{profile}: {str(exc)[:400]}")
            break
        finally:
            end_round(stack, ROBOT, pids)
    result.figure(f"{restarts.what}: rounds (a fresh profile every {RECOVERY_LIMIT} restarts)", round_)
    return restarts


def executors_stopped(stack: Stack) -> int:
    """How often the gateway logged that an executor of a ROS domain died (its nodes then get no
    answers until the gateway restarts: ros_gateway/domain.py, _spin)."""
    lines = stack.gateway.output().splitlines() if stack.gateway else []
    return sum(1 for line in lines if EXECUTOR_LINE in line and EXECUTOR_DIED in line)


def executor_failures(stack: Stack) -> int:
    """How often an executor failed inside a spin and spun on (ros_gateway/domain.py, _spin)."""
    lines = stack.gateway.output().splitlines() if stack.gateway else []
    return sum(1 for line in lines if EXECUTOR_LINE in line and "spinning on" in line)


def report_restarts(result: ScenarioResult, all_restarts: list[Restarts]) -> None:
    for restarts in all_restarts:
        result.notes.extend(restarts.failures)
        if restarts.unrecorded:
            result.notes.append(f"{restarts.what}: {restarts.unrecorded} times a node had no "
                                "process_restarted or no recovery record to active after the restart")
    fifty = next(r for r in all_restarts if r.count == max(x.count for x in all_restarts))
    median = fifty.back.median if fifty.back.values else float("inf")
    result.check(f"restart -> {fifty.count} nodes active again, median", median, f"< {RESTART_TARGET_S:g} s",
                 median < RESTART_TARGET_S, "s")
    lost = sum(len(r.failures) for r in all_restarts)
    result.check(f"restarts or rounds that failed ({RESTART_TIMEOUT_S:g} s each; notes say how)", lost, "= 0",
                 lost == 0)


# -- 2. the gateway at rest with 20 supervised processes -----------------------------------------
def cpu_share(pid: int, seconds: float) -> tuple[float, float]:
    """% of one core used by the process itself, and by its descendants together, over ``seconds``."""
    def children() -> float:
        total = 0.0
        for p in tree(pid)[1:]:
            try:
                total += cpu_seconds(p)
            except OSError:
                pass
        return total

    own, kids, began = cpu_seconds(pid), children(), time.monotonic()
    time.sleep(seconds)
    lasted = time.monotonic() - began
    return 100 * (cpu_seconds(pid) - own) / lasted, 100 * (children() - kids) / lasted


def at_rest(stack: Stack, label: str, profiles: list[dict], seconds: float, settle: float, result: ScenarioResult,
            pids: set[int], nodes: list[str] | None = None) -> float:
    """Run ``profiles`` on the rest robot; once running (and ``nodes`` listed with their state) and
    settled, the gateway's CPU and memory; then the profiles deleted. Returns the CPU share."""
    began = time.monotonic()
    in_site(stack, f"add_profiles({REST_ROBOT!r}, {profiles!r})")
    wait_running(stack, REST_ROBOT, [spec["name"] for spec in profiles], pids)
    if nodes:
        stack.wait_nodes(nodes, START_TIMEOUT_S, state="unconfigured")
    result.figure(f"{label}: profiles saved -> all running" + (", nodes listed" if nodes else ""),
                  time.monotonic() - began, "s")
    time.sleep(settle)
    load = loadavg()[0]
    share, children = cpu_share(stack.gateway.pid, seconds)
    result.figure(f"{label}: gateway CPU at rest (over {seconds:g} s)", share, "% of a core")
    result.figure(f"{label}: gateway RSS", rss_mb(stack.gateway.pid), "MB")
    result.figure(f"{label}: the supervised processes' CPU together, same window", children, "% of a core")
    result.figure(f"{label}: load average (1 min) then", load)
    result.figure(f"{label}: profiles deleted -> every process ended", end_round(stack, REST_ROBOT, pids), "s")
    return share


def measure_rest(stack: Stack, quick: bool, result: ScenarioResult, pids: set[int]) -> None:
    # 30 s: the gateway's longest periodic job (a re-read of every node's state) falls in the window once.
    seconds, settle = (5.0, 3.0) if quick else (30.0, 10.0)
    time.sleep(settle)
    idle, _ = cpu_share(stack.gateway.pid, seconds)
    result.figure(f"no supervised process: gateway CPU at rest (over {seconds:g} s)", idle, "% of a core")
    result.figure("no supervised process: gateway RSS", rss_mb(stack.gateway.pid), "MB")
    label = f"{REST_PROCESSES} demo robots (1 node each)"
    robots = [demo_robot(f"rest-{i:02d}", REST_DOMAIN, 1, f"{PREFIX}rest{i:02d}") for i in range(REST_PROCESSES)]
    nodes = [f"{REST_ROBOT}.{PREFIX}rest{i:02d}_000" for i in range(REST_PROCESSES)]
    share = at_rest(stack, label, robots, seconds, settle, result, pids, nodes)
    sleepers = [sleeper(f"sleep-{i:02d}") for i in range(REST_PROCESSES)]
    at_rest(stack, f"{REST_PROCESSES} sleep processes", sleepers, seconds, settle, result, pids)
    result.check(f"gateway CPU at rest with {REST_PROCESSES} supervised demo robots", share,
                 f"< {REST_CPU_TARGET:g} %", share < REST_CPU_TARGET, "%")


# -- the scenario --------------------------------------------------------------------------------
def run(ctx: BenchContext) -> ScenarioResult:
    result = ScenarioResult(NAME, TITLE, load_before=loadavg())
    samples = {1: 3, 50: 2} if ctx.quick else {1: 10, 50: 5}
    pids: set[int] = set()
    result.notes.append(f"each profile: {PYTHON} {' '.join(robot_args(DOMAIN, 1, 'P'))} (--generic 1 or 50); "
                        f"at rest: {REST_PROCESSES} such processes of 1 node each (real ROS processes), then "
                        f"{REST_PROCESSES} of `sleep {SLEEP_ARG}`")
    try:
        with ctx.stack(NAME, [(ROBOT, DOMAIN), (REST_ROBOT, REST_DOMAIN)]) as stack:
            store = Store(stack)
            try:
                with profiled(ctx, stack, NAME):
                    all_restarts = [measure_restarts(stack, store, count, n, result, pids)
                                    for count, n in samples.items()]
                    result.figure("load average (1 min) after the restarts", loadavg()[0])
                    measure_rest(stack, ctx.quick, result, pids)
            finally:
                store.close()
                died = executors_stopped(stack)
                result.figure("gateway executor failures survived (log: 'spinning on')", executor_failures(stack))
    finally:
        left = wait_gone(pids)
        for pid in left:  # the stack started them (through its gateway): none may outlive it
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        if left:
            print(f"supervised: demo robot processes left after the stack stopped, killed: {left}", flush=True)
    report_restarts(result, all_restarts)
    result.check("gateway executors that died (log: 'an executor of ROS domain N stopped')", died, "= 0", not died)
    result.figure("processes of this scenario left after the stack stopped", len(left))
    if left:
        result.notes.append(f"still running after the stack stopped (killed then): pids {left}")
    return result
