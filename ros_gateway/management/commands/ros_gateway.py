"""``manage.py ros_gateway``: the long-running agent that owns all ROS communication of its
robots. It needs only the site's Redis (REDIS_URL, with this gateway's own credentials) and
never opens the site's database."""
from __future__ import annotations

import asyncio
import os
import signal

from django.core.management.base import BaseCommand, CommandError

from ros_gateway.shared import protocol


class Command(BaseCommand):
    help = "Watch this gateway's robots (as the site configures them) and serve the site's lifecycle commands."
    # Nothing here may touch the database: no system checks (some read it), no migration check.
    requires_system_checks: list = []
    requires_migrations_checks = False

    def add_arguments(self, parser) -> None:
        parser.add_argument(
            "--name",
            default=os.environ.get("LIFECYCLE_GATEWAY_NAME", protocol.DEFAULT_GATEWAY),
            help="This gateway's name, as registered in the site (manage.py add_gateway NAME); default: "
            f"$LIFECYCLE_GATEWAY_NAME or {protocol.DEFAULT_GATEWAY!r}.",
        )

    def handle(self, *args, name: str, **options) -> None:
        os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        from django.conf import settings

        from ros_gateway.config import ConfigError, GatewayConfig, apply_dds
        from ros_gateway.service import AlreadyRunning, Gateway  # imports rclpy: only in this process

        try:
            config = GatewayConfig.load(name, settings)
        except ConfigError as exc:
            raise CommandError(str(exc)) from None
        apply_dds(config)  # before the first ROS participant reads the environment

        async def main() -> None:
            gateway = Gateway(config)
            loop = asyncio.get_running_loop()
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.add_signal_handler(sig, gateway.stop)
            await gateway.run()

        try:
            asyncio.run(main())
        except AlreadyRunning as exc:
            raise CommandError(str(exc)) from None
        self.stdout.write("ROS gateway stopped.")
