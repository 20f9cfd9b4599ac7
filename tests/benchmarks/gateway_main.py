"""The product's gateway (ros_gateway.service.Gateway, as ``python -m ros_gateway`` runs it)
plus a JSON file of its own counters, rewritten every half second, so the benchmark can see
what it received, dropped, handed to its outbox and published. Nothing of the gateway is
changed. (What is stored, the ingest process stores: see Stack.ingest_stats.)

    python -m tests.benchmarks.gateway_main NAME STATS_PATH
"""
from __future__ import annotations

import asyncio
import json
import logging
import os
import signal
import sys
import time
from pathlib import Path

REPORT_INTERVAL_S = 0.5


tasks_module = None  # ros_gateway.tasks, once Django is set up


def snapshot(gateway) -> dict:
    logs, buffer, tasks = gateway.logs, gateway.logs.buffer, tasks_module
    return {
        "time": time.time(),
        "monotonic": time.monotonic(),
        "logs_received": buffer.received,
        "logs_dropped": buffer.dropped,
        "logs_buffered": len(buffer),
        "logs_collected": logs.collected,
        "outbox": gateway.outbox.counters(),
        "published": gateway.relay.published,
        "publish_failures": gateway.relay.publish_failures,
        "commands_handled": gateway.commands.handled,
        "domains": sorted(gateway.domains),
        "nodes_known": len(gateway.registry.nodes),
        "nodes_alive": sum(1 for n in gateway.registry.nodes.values() if n.alive),
        "nodes_state_read": sum(1 for n in gateway.registry.nodes.values() if n.alive and n.state_read),
        "background_tasks": len(tasks._running),
        "liveness_probes": gateway.liveness.probes,
    }


async def report(gateway, path: Path) -> None:
    scratch = path.with_suffix(".tmp")
    while True:
        scratch.write_text(json.dumps(snapshot(gateway)))
        scratch.replace(path)
        await asyncio.sleep(REPORT_INTERVAL_S)


def main(name: str, stats_path: str) -> None:
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    # As ``python -m ros_gateway`` logs (its level from LIFECYCLE_LOG_LEVEL), with times.
    logging.basicConfig(level=os.environ.get("LIFECYCLE_LOG_LEVEL", "INFO").upper(),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from ros_gateway import tasks
    from ros_gateway.config import GatewayConfig
    from ros_gateway.service import Gateway

    global tasks_module
    tasks_module = tasks

    async def run() -> None:
        gateway = Gateway(GatewayConfig.load(name))
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, gateway.stop)
        reporter = asyncio.create_task(report(gateway, Path(stats_path)))
        try:
            await gateway.run()
        finally:
            reporter.cancel()

    asyncio.run(run())


if __name__ == "__main__":
    main(*sys.argv[1:3])
