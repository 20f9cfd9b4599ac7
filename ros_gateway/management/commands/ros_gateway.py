"""``manage.py ros_gateway``: the long-running worker that owns all ROS communication."""
from __future__ import annotations

import asyncio
import os
import signal

from django.core.management.base import BaseCommand, CommandError


class Command(BaseCommand):
    help = "Watch the registered robots' ROS domains and serve the site's lifecycle commands."

    def add_arguments(self, parser) -> None:
        parser.add_argument(
            "--name",
            default=os.environ.get("LIFECYCLE_GATEWAY_NAME", "gateway"),
            help="Name under which this gateway reports its heartbeat.",
        )

    def handle(self, *args, name: str, **options) -> None:
        os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        from django.conf import settings

        from ros_gateway import store
        from ros_gateway.service import Gateway  # imports rclpy: only in this process

        twin = store.running_twin(name, settings.LIFECYCLE["GATEWAY_OFFLINE_AFTER"])
        if twin:
            raise CommandError(
                f"A gateway named {name!r} is already running ({twin}). Stop it, or start this one "
                "with --name OTHER to watch other robots."
            )

        async def main() -> None:
            gateway = Gateway(name)
            loop = asyncio.get_running_loop()
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.add_signal_handler(sig, gateway.stop)
            await gateway.run()

        asyncio.run(main())
        self.stdout.write("ROS gateway stopped.")
