"""Bring-up of one robot's nodes to active, for growing node counts, two ways:

* sequential API calls: ``POST .../transition`` configure then activate, node after node,
  as a script without a group operation does (docs/api.md, "Automation example");
* the group operation: ``POST /api/v1/robots/{name}/operations`` with ``bringup`` and the
  nodes listed, waiting for the run's end (``?wait=``).

The gateway makes a node's service clients on its first call, and a new client needs a
moment to match its service: so the first bring-up of a robot after discovery ("cold") is
measured apart, on robots not touched before, and the growth from 10 to 100 nodes on a robot
that has been brought up once ("warm"), smaller sizes twice (medians). Between measurements
the nodes are reset to unconfigured (group ``reset``, not measured).
"""
from __future__ import annotations

import statistics
import time

from tests.benchmarks.harness import Stack
from tests.benchmarks.processes import BenchError
from tests.benchmarks.report import ScenarioResult, Series

RUN_WAIT_S = 240
LINEAR_SLACK = 1.2  # "linear or better": time per node at the largest size within 1.2x of the smallest


def sequential(stack: Stack, keys: list[str], calls: Series) -> float:
    """Configure then activate each node in turn; returns the wall time in seconds."""
    began = time.perf_counter()
    for key in keys:
        for label in ("configure", "activate"):
            response = stack.api.transition(key, label)
            if response.status != 200:
                raise BenchError(f"bring-up: {label} {key} answered {response.status}: {response.body[:300]!r}")
            calls.add(response.ms)
    return time.perf_counter() - began


def group_run(stack: Stack, robot: str, operation: str, names: list[str]) -> tuple[float, dict]:
    """One group operation over ``names``, waited for; returns (wall seconds, the run)."""
    body = {"operation": operation, "policy": "continue", "timeout": 5, "nodes": names}
    response = stack.api.post_json(f"/api/v1/robots/{robot}/operations?wait={RUN_WAIT_S}", body)
    if response.status != 200:
        raise BenchError(f"{operation} of {len(names)} nodes answered {response.status}: {response.body[:300]!r}")
    run = response.json()["run"]
    failed = [r for r in run["results"] if r["outcome"] not in ("succeeded", "skipped")]
    if run["status"] != "succeeded" or failed:
        raise BenchError(f"{operation} run ended {run['status']}: {failed[:3]}")
    return response.ms / 1000, run


def reset(stack: Stack, robot: str, names: list[str]) -> None:
    group_run(stack, robot, "reset", names)
    stack.wait_nodes([f"{robot}.{n.strip('/')}" for n in names], 60, state="unconfigured")


def grow_check(result: ScenarioResult, what: str, per_node: dict[int, float]) -> None:
    small, large = min(per_node), max(per_node)
    growth = per_node[large] / per_node[small]
    total = per_node[large] * large
    result.figure(f"{what}: time per node at {large} / at {small} (1.0 = linear)", growth, "x")
    result.check(f"{what}: {large} nodes", total, "< 5 s", total < 5, "s")
    result.check(f"{what}: grows linearly or better", growth, f"<= {LINEAR_SLACK} x", growth <= LINEAR_SLACK, "x")


def robot_nodes(stack: Stack, robot: str, count: int) -> tuple[list[str], list[str]]:
    """Keys and ROS names of the robot's first ``count`` nodes by name."""
    nodes = sorted(stack.nodes(robot), key=lambda n: n["name"])
    if len(nodes) < count:
        raise BenchError(f"{robot} lists {len(nodes)} nodes, fewer than {count}")
    return [n["id"] for n in nodes[:count]], [n["name"] for n in nodes[:count]]


def measure_cold(stack: Stack, group_robot: str, api_robot: str, count: int, result: ScenarioResult) -> None:
    """The first bring-up of whole robots after discovery: one by group run, one by API calls."""
    _, names = robot_nodes(stack, group_robot, count)
    seconds, _ = group_run(stack, group_robot, "bringup", names)
    result.figure(f"cold: first group bringup of {count} nodes", seconds, "s")
    keys, _ = robot_nodes(stack, api_robot, count)
    seconds = sequential(stack, keys, result.new_series(f"cold: first sequential bring-up of {count}: each call"))
    result.figure(f"cold: first sequential API bring-up of {count} nodes", seconds, "s")


def measure_warm(stack: Stack, robot: str, sizes: list[int], result: ScenarioResult) -> None:
    keys, names = robot_nodes(stack, robot, max(sizes))
    group_run(stack, robot, "bringup", names)  # warm-up: every node's clients made and matched
    reset(stack, robot, names)
    by_api: dict[int, float] = {}
    by_group: dict[int, float] = {}
    for size in sizes:
        repeats = 1 if size == max(sizes) else 2
        calls = result.new_series(f"sequential bring-up of {size}: each API call")
        steps = result.new_series(f"group bringup of {size}: each step (gateway)")
        api_s, group_s = [], []
        for _ in range(repeats):
            api_s.append(sequential(stack, keys[:size], calls))
            reset(stack, robot, names[:size])
            seconds, run = group_run(stack, robot, "bringup", names[:size])
            group_s.append(seconds)
            steps.values.extend(step["duration_ms"] for node in run["results"] for step in node["steps"])
            reset(stack, robot, names[:size])
        by_api[size] = statistics.median(api_s) / size
        by_group[size] = statistics.median(group_s) / size
        result.figure(f"sequential API bring-up of {size} nodes", by_api[size] * size, "s")
        result.figure(f"group bringup run of {size} nodes", by_group[size] * size, "s")
    grow_check(result, "sequential API bring-up", by_api)
    grow_check(result, "group bringup", by_group)
