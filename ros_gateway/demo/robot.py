"""Run a simulated AGV: several demo nodes in one process and one ROS context.

Example::

    python -m ros_gateway.demo.robot --domain 151 --namespace /agv1 \\
        --param flaky_node.failure_mode:=slow_configure --autostart activate

Prints ``demo robot ready: <fully qualified node names>`` on stdout once the nodes exist,
exits 0 on SIGINT/SIGTERM. Arguments after ``--ros-args`` go to rclpy unchanged.
Each demo node gets its own executor thread by default (``--executor shared`` for one
MultiThreadedExecutor); a slow transition of one node never blocks another.
If ``ROS_AUTOMATIC_DISCOVERY_RANGE`` is unset it defaults to ``LOCALHOST`` here.

Diagnostics (``diagnostics``, relative to the namespace): the lidar and flaky nodes publish
statuses, and a plain ``battery_monitor`` node (not in the ready line; ``--no-battery`` leaves it
out, for a robot split over several processes) a simulated battery; ``--diagnostics-agg`` adds a
``diagnostic_aggregator`` node publishing ``diagnostics_agg``.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
import traceback
from typing import Any, Optional, Sequence

import rclpy
import yaml
from rclpy.context import Context
from rclpy.executors import Executor, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn
from rclpy.logging import LoggingSeverity
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.signals import SignalHandlerOptions

from .base import DemoLifecycleNode
from .diagnostics import BatteryMonitor
from .diagnostics_agg import DiagnosticAggregator
from .generic import GenericNode
from .nodes import DEFAULT_NODES, NODE_CLASSES

AUTOSTART_CHOICES = ("none", "configure", "activate")
LOG_LEVELS = ("debug", "info", "warn", "error", "fatal")
SHUTDOWN_DEADLINE_S = 2.5
# destroying a node costs O(all endpoints) in rmw_fastrtps (graph updates): ~40 ms at 100 nodes
SHUTDOWN_S_PER_NODE = 0.1
GENERIC_PER_EXECUTOR = 10


def parse_param(spec: str) -> tuple[str, str, Any]:
    """Parse ``NODE.PARAM:=VALUE`` (VALUE as a YAML scalar or list) into a tuple."""
    key, sep, raw = spec.partition(":=")
    node, dot, name = key.partition(".")
    if not sep or not dot or not node or not name:
        raise argparse.ArgumentTypeError(f"expected NODE.PARAM:=VALUE, got {spec!r}")
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError:
        value = raw
    if value is None or not isinstance(value, (bool, int, float, str, list, dict)):
        value = raw
    if isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"{spec!r}: value must be a scalar or a list")
    return node, name, value


def parse_args(argv: Sequence[str]) -> tuple[argparse.Namespace, list[str]]:
    """Split off ``--ros-args ...`` and parse the rest; return (options, ros args)."""
    argv = list(argv)
    ros_args: list[str] = []
    if "--ros-args" in argv:
        i = argv.index("--ros-args")
        argv, ros_args = argv[:i], argv[i:]
    parser = argparse.ArgumentParser(
        prog="python -m ros_gateway.demo.robot",
        description="Simulated AGV: demo ROS 2 (lifecycle) nodes in one process.",
    )
    parser.add_argument("--domain", type=int, default=None, help="ROS domain id (default: $ROS_DOMAIN_ID or 0)")
    parser.add_argument("--namespace", default="", help="namespace for all nodes, e.g. /agv1")
    parser.add_argument(
        "--nodes",
        default=",".join(DEFAULT_NODES),
        help="comma-separated subset of: " + ", ".join(NODE_CLASSES) + " (may be empty with --generic)",
    )
    parser.add_argument(
        "--param",
        action="append",
        type=parse_param,
        default=[],
        metavar="NODE.PARAM:=VALUE",
        help="initial parameter (NODE may be * for all nodes); repeatable",
    )
    parser.add_argument(
        "--autostart",
        choices=AUTOSTART_CHOICES,
        default="none",
        help="drive the lifecycle nodes to this state right after start",
    )
    parser.add_argument(
        "--generic", type=int, default=0, metavar="COUNT", help="also create COUNT minimal lifecycle nodes"
    )
    parser.add_argument(
        "--generic-prefix", default="generic", help="name prefix of the generic nodes (<prefix>_000 ...)"
    )
    parser.add_argument(
        "--log-level",
        choices=LOG_LEVELS,
        default="info",
        help="logger level of every node (debug enables periodic details)",
    )
    parser.add_argument(
        "--executor",
        choices=("per-node", "shared"),
        default="per-node",
        help="per-node (default): one executor per demo node and "
        f"one per {GENERIC_PER_EXECUTOR} generic nodes (rclpy executors "
        "rebuild their wait set over all their nodes on every wake-up, so "
        "this costs far less CPU); shared: one MultiThreadedExecutor",
    )
    parser.add_argument("--threads", type=int, default=4, help="worker threads of the shared executor (default 4)")
    parser.add_argument(
        "--diagnostics-agg",
        action="store_true",
        help=f"also run a {DiagnosticAggregator.NAME} node: the robot's diagnostics as a tree on diagnostics_agg",
    )
    parser.add_argument(
        "--no-battery",
        action="store_true",
        help=f"no {BatteryMonitor.NAME} node (for a further process of a robot whose battery another one reports)",
    )
    opts = parser.parse_args(argv)
    names = [n.strip() for n in opts.nodes.split(",") if n.strip()]
    unknown = [n for n in names if n not in NODE_CLASSES]
    if unknown:
        parser.error(f"unknown node(s): {', '.join(unknown)}; choose from " + ", ".join(NODE_CLASSES))
    if len(set(names)) != len(names):
        parser.error("--nodes lists a node twice")
    if opts.generic < 0:
        parser.error("--generic must be >= 0")
    if not names and not opts.generic:
        parser.error("no nodes to run")
    opts.node_names = names + [f"{opts.generic_prefix}_{i:03d}" for i in range(opts.generic)]
    opts.helper_classes = [c for c, on in ((BatteryMonitor, not opts.no_battery),
                                           (DiagnosticAggregator, opts.diagnostics_agg)) if on]
    missing = {n for n, _, _ in opts.param} - set(opts.node_names) - {c.NAME for c in opts.helper_classes} - {"*"}
    if missing:
        parser.error(f"--param for node(s) not started: {', '.join(sorted(missing))}")
    if opts.domain is None:
        env = os.environ.get("ROS_DOMAIN_ID", "").strip()
        opts.domain = int(env) if env.isdigit() else 0
    if not 0 <= opts.domain <= 232:
        parser.error("--domain must be between 0 and 232")
    if opts.threads < 1:
        parser.error("--threads must be >= 1")
    ns = opts.namespace.strip()
    opts.namespace = "" if ns in ("", "/") else "/" + ns.strip("/")
    return opts, ros_args


def schedule_autostart(node: LifecycleNode, target: str) -> None:
    """Trigger configure (and activate) from a one-shot timer in the node's own group."""
    timer: Optional[Any] = None

    def run() -> None:
        assert timer is not None
        timer.cancel()
        node.destroy_timer(timer)
        log = node.get_logger()
        try:
            if node.trigger_configure() != TransitionCallbackReturn.SUCCESS:
                log.warn("autostart: configure did not succeed")
                return
            if target == "activate" and node.trigger_activate() != TransitionCallbackReturn.SUCCESS:
                log.warn("autostart: activate did not succeed")
        except _rclpy.RCLError as exc:
            log.warn(f"autostart: transition not possible: {str(exc).split(',')[0]}")

    timer = node.create_timer(0.01, run)


def spin_until(executor: Executor, stop: threading.Event) -> None:
    """Spin `executor` until `stop` is set; a raising callback does not end the loop."""
    while not stop.is_set():
        try:
            executor.spin()
        except Exception:  # noqa: BLE001 - e.g. an exception escaping a topic callback
            print("demo robot: callback raised:\n" + traceback.format_exc(), file=sys.stderr, flush=True)


def make_executors(nodes: list[Node], opts: argparse.Namespace) -> list[Executor]:
    """Create the executors (see ``--executor``) and add the nodes to them."""
    context = nodes[0].context
    if opts.executor == "shared":
        executor: Executor = (
            MultiThreadedExecutor(num_threads=opts.threads, context=context)
            if opts.threads > 1
            else SingleThreadedExecutor(context=context)
        )
        for node in nodes:
            executor.add_node(node)
        return [executor]
    executors: list[Executor] = []
    generic = [n for n in nodes if isinstance(n, GenericNode)]
    for node in nodes:
        if isinstance(node, GenericNode):
            continue
        # a MultiThreadedExecutor costs about twice the CPU per callback: only for nodes
        # with slow transitions, so that their get_state keeps answering meanwhile
        threads = getattr(node, "EXECUTOR_THREADS", 1)
        executor = (
            MultiThreadedExecutor(num_threads=threads, context=context)
            if threads > 1
            else SingleThreadedExecutor(context=context)
        )
        executor.add_node(node)
        executors.append(executor)
    for i in range(0, len(generic), GENERIC_PER_EXECUTOR):
        executor = SingleThreadedExecutor(context=context)
        for node in generic[i : i + GENERIC_PER_EXECUTOR]:
            executor.add_node(node)
        executors.append(executor)
    return executors


def shut_down(ctx: Context, nodes: list[Node], executors: list[Executor], threads: list[threading.Thread]) -> None:
    """Stop spinning, destroy the nodes (so peers see them leave), shut the context down.

    A watchdog ends the process (exit code 0) if this takes unexpectedly long.
    """

    def deadline() -> None:
        print("demo robot: clean shutdown took too long, exiting anyway", file=sys.stderr, flush=True)
        os._exit(0)

    watchdog = threading.Timer(SHUTDOWN_DEADLINE_S + SHUTDOWN_S_PER_NODE * len(nodes), deadline)
    watchdog.daemon = True
    watchdog.start()
    for node in nodes:
        if isinstance(node, DemoLifecycleNode):
            node.request_abort()
    for ex in executors:
        ex.shutdown(timeout_sec=0)
    for thread in threads:
        thread.join(timeout=1.0)
    for node in nodes:
        node.destroy_node()
    rclpy.shutdown(context=ctx)
    for ex in executors:
        pool = getattr(ex, "_executor", None)  # MultiThreadedExecutor's worker pool
        if pool is not None:
            pool.shutdown(wait=True)
    watchdog.cancel()


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Entry point; returns the process exit code."""
    opts, ros_args = parse_args(sys.argv[1:] if argv is None else argv)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    stop = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)

    ctx = Context()
    rclpy.init(
        args=["robot", *ros_args], context=ctx, domain_id=opts.domain, signal_handler_options=SignalHandlerOptions.NO
    )
    severity = getattr(LoggingSeverity, opts.log_level.upper())
    nodes: list[Node] = []
    # plain helper nodes (battery, aggregator): spun and shut down with the demo nodes, but not
    # in the ready line, which names the demo nodes only
    helpers: list[Node] = []
    try:
        for name in opts.node_names:
            overrides = [Parameter(p, value=v) for n, p, v in opts.param if n in (name, "*")]
            cls = NODE_CLASSES.get(name, GenericNode)
            node = cls(name, namespace=opts.namespace, context=ctx, parameter_overrides=overrides)
            node.get_logger().set_level(severity)
            nodes.append(node)
        for helper in opts.helper_classes:
            name = helper.NAME
            overrides = [Parameter(p, value=v) for n, p, v in opts.param if n == name]
            node = helper(name, namespace=opts.namespace, context=ctx, parameter_overrides=overrides)
            node.get_logger().set_level(severity)
            helpers.append(node)
    except Exception as exc:  # noqa: BLE001 - e.g. a parameter override out of range
        print(f"demo robot: cannot create node {name!r}: {type(exc).__name__}: {exc}", file=sys.stderr, flush=True)
        for node in nodes + helpers:
            node.destroy_node()
        rclpy.shutdown(context=ctx)
        return 2

    executors = make_executors(nodes + helpers, opts)
    if opts.autostart != "none":
        for node in nodes:
            if isinstance(node, LifecycleNode):
                schedule_autostart(node, opts.autostart)
    threads = [
        threading.Thread(target=spin_until, args=(ex, stop), daemon=True, name=f"spin-{i}")
        for i, ex in enumerate(executors)
    ]
    for thread in threads:
        thread.start()
    print("demo robot ready: " + ",".join(n.get_fully_qualified_name() for n in nodes), flush=True)
    while not stop.wait(0.5):
        pass
    shut_down(ctx, nodes + helpers, executors, threads)
    return 0


if __name__ == "__main__":
    sys.exit(main())
