"""The diagnostics page's socket: told by the ingest process which statuses of its robot changed
(ingest/diagnostic_facts.py), it draws the tree again and sends only the rows that differ from what the
page shows (the whole tree when statuses came or went), with the counts. Changes close together are
drawn once: a level change within GATHER_S, a freshness-only update within QUIET_S."""
from __future__ import annotations

from channels.db import database_sync_to_async
from django.template.loader import render_to_string

from lifecycle_site.dashboard.consumers import LiveConsumer
from lifecycle_site.dashboard.diagnostic_views import tree_context
from lifecycle_site.dashboard.gathered import GatheredDraws
from lifecycle_site.diagnostics.models import page_group
from lifecycle_site.prefix import script_prefix

GATHER_S = 0.03
QUIET_S = 1.0


class DiagnosticsConsumer(GatheredDraws, LiveConsumer):
    async def prepare(self) -> bool:
        self.robot = await self.route_robot()
        if self.robot is None:
            return False
        self.groups_to_join = [page_group(self.robot.id)]
        self.shown: dict[str, str] | None = None  # row id -> its HTML, as the page has it
        self.counts = ""
        return True

    async def send_snapshot(self) -> None:
        await self.draw()  # what changed since the page was drawn

    async def diagnostics_changed(self, event: dict) -> None:
        self.soon(GATHER_S if event.get("names") else QUIET_S)

    async def draw(self) -> None:
        def render() -> tuple[list[tuple[str, str]], str, str]:
            context = {**tree_context(self.robot), "can_operate": self.can_operate}
            with script_prefix(self.prefix):
                rows = [(row["id"], render_to_string("dashboard/_diagnostic_row.html", {**context, "row": row,
                                                                                           "oob": True}))
                        for row in context["rows"]]
                counts = render_to_string("dashboard/_diagnostic_counts.html", context)
                whole = "" if self.shown is not None and [r for r, _ in rows] == list(self.shown) else \
                    render_to_string("dashboard/_diagnostic_rows.html", context)
            return rows, counts, whole

        rows, counts, whole = await database_sync_to_async(render, thread_sensitive=False)()
        parts = []
        if counts != self.counts:
            self.counts = counts
            parts.append(f'<div id="diagnostics-counts" hx-swap-oob="innerHTML">{counts}</div>')
        if whole:
            parts.append(f'<ul id="diagnostics-live" hx-swap-oob="innerHTML">{whole}</ul>')
        else:
            parts += [html for row_id, html in rows if self.shown.get(row_id) != html]
        self.shown = dict(rows)
        if parts:
            await self.send(text_data="".join(parts))

    async def disconnect(self, code: int) -> None:
        self.stop_drawing()
        await super().disconnect(code)
