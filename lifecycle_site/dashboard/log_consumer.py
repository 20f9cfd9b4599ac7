"""The log console's socket: ``ws/logs/node/<key>/`` or ``ws/logs/robot/<name>/``, records as JSON
(bounding, filtering and pausing a fast stream is the browser's job there: static/js/logs.js)."""
from __future__ import annotations

import json

from channels.db import database_sync_to_async
from django.template.loader import render_to_string

from lifecycle_site.dashboard import snapshots
from lifecycle_site.dashboard.consumers import LiveConsumer
from lifecycle_site.prefix import script_prefix


class LogConsumer(LiveConsumer):
    """``ws/logs/node/<key>/`` or ``ws/logs/robot/<name>/``: records as JSON."""

    async def prepare(self) -> bool:
        kwargs = self.scope["url_route"]["kwargs"]
        self.target = (kwargs["scope"], kwargs["name"])
        group = await database_sync_to_async(snapshots.log_group)(*self.target)
        self.groups_to_join = [group] if group else []
        return group is not None

    def gateway_views(self) -> list[dict]:
        scope, name = self.target
        return snapshots.node_gateway(name) if scope == "node" else snapshots.robot_gateway(name)

    async def node_logs(self, event: dict) -> None:
        await self.send(text_data=json.dumps({"records": event["records"]}))

    async def node_state(self, event: dict) -> None:
        pass

    async def node_parameters(self, event: dict) -> None:
        pass

    async def run_progress(self, event: dict) -> None:
        pass

    async def check_runs(self) -> None:
        pass

    async def send_gateway_status(self, offline: list[dict]) -> None:
        with script_prefix(self.prefix):
            banner = render_to_string("dashboard/_gateway_banner.html", {"offline_gateways": offline})
        await self.send(text_data=json.dumps({"gateway_online": not offline, "gateway_banner": banner}))
