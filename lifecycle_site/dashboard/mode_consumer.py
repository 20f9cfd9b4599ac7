"""The Modes page's socket: the robot's drift from its mode and its readiness, sent again as soon
as one of its nodes changes state or a run of it moves on (its robot's group), and every few
seconds for what has no push (parameter values, topic rates). A burst of node updates (a mode
applied to 50 nodes) is drawn once: updates that come while one is being drawn make one more."""
from __future__ import annotations

from channels.db import database_sync_to_async
from django.template.loader import render_to_string

from lifecycle_site.dashboard.consumers import LiveConsumer
from lifecycle_site.dashboard.gathered import GatheredDraws
from lifecycle_site.dashboard.mode_views import live_context
from lifecycle_site.prefix import script_prefix
from ros_gateway.shared import protocol

GATHER_S = 0.05  # node updates this close together are drawn once


class ModesConsumer(GatheredDraws, LiveConsumer):
    async def prepare(self) -> bool:
        self.robot = await self.route_robot()
        if self.robot is None:
            return False
        self.groups_to_join = [protocol.robot_group(self.robot.id)]
        self.sent: str | None = None
        return True

    async def send_snapshot(self) -> None:
        await self.draw()

    async def check_runs(self) -> None:  # every GATEWAY_CHECK_S: values and rates have no push
        await self.draw()

    async def node_state(self, event: dict) -> None:
        self.soon(GATHER_S)

    async def run_progress(self, event: dict) -> None:
        self.soon(GATHER_S)

    async def draw(self) -> None:
        def render() -> tuple[str, str]:
            context = live_context(self.robot)
            with script_prefix(self.prefix):
                return context["seen"], render_to_string("dashboard/_modes_live_oob.html", context)

        seen, html = await database_sync_to_async(render, thread_sensitive=False)()
        if seen != self.sent:
            self.sent = seen
            await self.send(text_data=html)

    async def disconnect(self, code: int) -> None:
        self.stop_drawing()
        await super().disconnect(code)
