"""``python -m ros_gateway [--name NAME]``: the long-running agent that owns all ROS communication
of its robots. It reads only its own environment (config.py: the site's Redis with this gateway's
own credentials, timings, DDS settings), never the site's settings or database."""
from __future__ import annotations

import argparse
import asyncio
import logging
import os
import signal
import sys

from ros_gateway.shared import environment, protocol

LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")


def arguments(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m ros_gateway",
        description="Watch this gateway's robots (as the site configures them) and serve the site's lifecycle "
        "commands. Settings come from the environment: docs/networks.md and docker/README.md list them.")
    parser.add_argument(
        "--name", default=environment.text("LIFECYCLE_GATEWAY_NAME", protocol.DEFAULT_GATEWAY),
        help="This gateway's name, as registered in the site (manage.py add_gateway NAME); default: "
        f"$LIFECYCLE_GATEWAY_NAME or {protocol.DEFAULT_GATEWAY!r}.")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    options = arguments(argv)
    level = environment.text("LIFECYCLE_LOG_LEVEL", "INFO").upper()
    logging.basicConfig(level=level if level in LOG_LEVELS else "INFO",
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    from ros_gateway.config import ConfigError, GatewayConfig, apply_dds
    from ros_gateway.service import AlreadyRunning, Gateway  # imports rclpy: only in this process

    try:
        config = GatewayConfig.load(options.name)
    except ConfigError as exc:
        sys.stderr.write(f"{exc}\n")
        return 2
    apply_dds(config)  # before the first ROS participant reads the environment

    async def run() -> None:
        gateway = Gateway(config)
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, gateway.stop)
        await gateway.run()

    try:
        asyncio.run(run())
    except AlreadyRunning as exc:
        sys.stderr.write(f"{exc}\n")
        return 1
    sys.stdout.write("ROS gateway stopped.\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
