"""Scenario 10: state timelines over a big audit log. 100,000 transition records and 1,000
absences (a node gone for a moment) over the last week for five nodes of one robot, written
into the scenario's real SQLite database, then the node timeline page, the robot timeline page
and both timeline API calls, each asked for the last hour, day and week through daphne (the
real HTTP server; the browser's session for the pages, a bearer token for the API), 30 times
each.

Target (issue 13, section 5): no page over 300 ms (checked on the p95 of each series).

    python -m tests.benchmarks.timeline seed ROBOT     (run by the scenario with the stack's
                                                        environment: writes the records)
"""
from __future__ import annotations

import random
import sys
import time
from datetime import timedelta

from tests.benchmarks.harness import BenchContext
from tests.benchmarks.processes import PYTHON, BenchError, run_manage
from tests.benchmarks.report import ScenarioResult, percentile
from tests.benchmarks.system import cpu_seconds, loadavg, tree

NAME = "timeline"
TITLE = ("10. State timeline: node page, robot page and API over 100,000 audit records and 1,000 absences "
         "(a week, 5 nodes)")
ROBOT = "bench-timeline"
DOMAIN = 126  # registered only: no robot process runs; shared with load and quiet, run one after the other
NODES = 5
RECORDS = 100_000
ABSENCE_EVERY = 100  # of a node's records: each node goes away 200 times in the week
REQUESTS = 30
TARGET_MS = 300.0
WINDOWS = ("hour", "day", "week")
# A node walks this cycle; one attempt in 50 fails (the node stays where it was), one in 400
# times out (its state is then unknown), one in 300 is a change made by another tool.
CYCLE = [("configure", 1, 1, 2), ("activate", 3, 2, 3), ("deactivate", 4, 3, 2), ("cleanup", 2, 2, 1)]


def seed(robot_name: str, nodes: int = NODES, records: int = RECORDS, days: float = 7.0) -> int:
    """Write the robot, its nodes (desired state active) and ``records`` audit records spread
    evenly over the last ``days`` (needs Django set up). Returns how many were written."""
    from django.utils import timezone

    from lifecycle_site.audit.models import TransitionRecord
    from lifecycle_site.fleet.models import ManagedNode, NodeAbsence, Robot
    from ros_gateway.shared import state_machine as sm

    now = timezone.now()
    began = now - timedelta(days=days)
    robot = Robot.objects.get(name=robot_name)
    made = [ManagedNode.objects.create(robot=robot, name=f"/timeline_node_{i}", alive=True, state_id=sm.UNCONFIGURED,
                                       state_label="unconfigured", first_seen=began - timedelta(hours=1),
                                       last_seen=now, state_changed=began - timedelta(hours=1),
                                       desired_state="active") for i in range(nodes)]
    rng = random.Random(13)
    step = timedelta(days=days) / records
    batch: list[TransitionRecord] = []
    absences: list[NodeAbsence] = []
    position = [0] * nodes
    for i in range(records):
        n = i % nodes
        node = made[n]
        label, transition_id, start, goal = CYCLE[position[n] % len(CYCLE)]
        at = began + step * i
        outcome, result, source = "succeeded", goal, "api"
        draw = rng.random()
        if draw < 0.02:
            outcome, result = "failed", start
        elif draw < 0.0225:
            outcome, result = "timed_out", None
        elif draw < 0.0258:
            source, outcome = "external", "observed"
        if result == goal:
            position[n] += 1
        elif result is None:
            position[n] = 0  # its state not read back: the next attempt starts from unconfigured
        took = rng.uniform(0.005, 0.08)
        result_label, start_label = (sm.state_label(result) if result is not None else ""), sm.state_label(start)
        batch.append(TransitionRecord(
            node=node, robot=robot, robot_name=robot.name, node_name=node.name, transition_id=transition_id,
            transition_label=label, start_state_id=start, start_state_label=start_label, goal_state_id=goal,
            goal_state_label=sm.state_label(goal), result_state_id=result, result_state_label=result_label,
            outcome=outcome, source=source, requested_at=at, completed_at=at + timedelta(seconds=took),
            duration_ms=took * 1000, requested_by_name="bench" if source == "api" else "",
        ))
        if (i // nodes) % ABSENCE_EVERY == ABSENCE_EVERY - 1:  # away between two of its records
            absences.append(NodeAbsence(node=node, gone_at=at + step * 0.2, back_at=at + step * 0.8,
                                        reason=("", "unreachable", "process_lost")[rng.randrange(3)]))
        if len(batch) == 5000:
            TransitionRecord.objects.bulk_create(batch)
            batch.clear()
    TransitionRecord.objects.bulk_create(batch)
    NodeAbsence.objects.bulk_create(absences)
    for node in made:  # its row says where the last record left it
        last = TransitionRecord.objects.filter(node=node).order_by("-requested_at").first()
        state = last.result_state_id if last and last.result_state_id is not None else sm.UNCONFIGURED
        ManagedNode.objects.filter(pk=node.pk).update(state_id=state, state_label=sm.state_label(state),
                                                      state_changed=last.completed_at if last else None)
    return TransitionRecord.objects.filter(robot=robot).count()


def run(ctx: BenchContext) -> ScenarioResult:
    result = ScenarioResult(NAME, TITLE, load_before=loadavg())
    requests = 10 if ctx.quick else REQUESTS
    with ctx.stack(NAME, [(ROBOT, DOMAIN)]) as stack:
        began = time.monotonic()
        out = run_manage(stack.env, "shell", "-c",
                         f"from tests.benchmarks.timeline import seed; print(seed({ROBOT!r}))", timeout=600)
        result.figure("audit records written", float(out.strip().splitlines()[-1]))
        result.figure("writing them took", time.monotonic() - began, "s")
        key = f"{ROBOT}.timeline_node_0"
        targets = []
        for window in WINDOWS:
            targets += [
                (f"node page, {window}", stack.web, f"/nodes/{key}/timeline/?window={window}"),
                (f"robot page, {window}", stack.web, f"/robots/{ROBOT}/timeline/?window={window}"),
                (f"API node, {window}", stack.api, f"/api/v1/nodes/{key}/timeline?window={window}"),
                (f"API robot, {window}", stack.api, f"/api/v1/robots/{ROBOT}/timeline?window={window}"),
            ]
        series = {name: result.new_series(f"{name} (daphne, keep-alive)") for name, _, _ in targets}
        # The server's own CPU time per request: what a request costs whatever else the machine
        # runs (wall times grow with the machine's load; this one much less).
        cpu = {name: result.new_series(f"{name}: daphne CPU per request") for name, _, _ in targets}
        server = tree(stack.site.pid)
        for _name, client, path in targets:  # one warm-up each: templates, the connection
            answer = client.get(path)
            if answer.status != 200:
                raise BenchError(f"GET {path} answered {answer.status}: {answer.body[:300]!r}")
        for _ in range(requests):  # interleaved, so a disturbance of the machine hits all alike
            for name, client, path in targets:
                used = sum(cpu_seconds(pid) for pid in server)
                answer = client.get(path)
                cpu[name].add((sum(cpu_seconds(pid) for pid in server) - used) * 1000)
                if answer.status != 200:
                    raise BenchError(f"GET {path} answered {answer.status}: {answer.body[:300]!r}")
                series[name].add(answer.ms)
        sizes = {name: len(client.get(path).body) for name, client, path in targets if "week" in name}
        for name, size in sizes.items():
            result.figure(f"{name}: answer size", size / 1024, "KiB")
    walls = [s for s in result.series if "CPU" not in s.name]
    worst = max(percentile(s.values, 95) for s in walls)
    slowest = max(walls, key=lambda s: percentile(s.values, 95))
    result.notes.append(f"slowest p95: {slowest.name}")
    result.notes.append("CPU per request is read from /proc in ticks of 10 ms: single values are coarse, "
                        "their median and mean are not")
    result.check("p95 of every page and API call", worst, f"< {TARGET_MS:g}", worst < TARGET_MS, "ms")
    heaviest = max(sum(s.values) / len(s.values) for s in result.series if "CPU" in s.name)
    result.check("mean daphne CPU per request, heaviest call", heaviest, f"< {TARGET_MS:g}", heaviest < TARGET_MS,
                 "ms")
    return result


if __name__ == "__main__" and len(sys.argv) == 3 and sys.argv[1] == "seed":
    import django

    django.setup()
    print(seed(sys.argv[2]))
elif __name__ == "__main__":
    sys.exit(f"usage: {PYTHON} -m tests.benchmarks.timeline seed ROBOT")
