"""The fleet page's socket and its collapsed robots (snapshots.fleet: robots of a large fleet
show their counts by state, not their rows, until the page opens them)."""
from __future__ import annotations

import asyncio
import json

from channels.db import database_sync_to_async
from django.template.loader import render_to_string

from lifecycle_site.dashboard import snapshots
from lifecycle_site.prefix import script_prefix


class CollapsedRobots:
    """For FleetConsumer: the counts of the robots the page shows collapsed, kept from the node
    updates and sent at most every SUMMARY_DELAY_S, and which robots the page has opened
    (fleet.js says so on connect and on each toggle). fleet_html() fills ``collapsible``,
    ``collapsed`` (robot name -> {node key: row status}) and ``known``."""

    SUMMARY_DELAY_S = 0.3
    prefix: str
    can_operate: bool
    collapsible: set[str]
    collapsed: dict[str, dict[str, str]]
    known: set[str]
    dirty: set[str]
    flusher: asyncio.Task | None = None
    # (send() is the consumer's: this class comes first in its bases, so it defines none.)

    def counted(self, node: dict) -> bool:
        """Whether ``node`` belongs to a robot shown collapsed: then its counts are sent soon."""
        statuses = self.collapsed.get(node["robot"])
        if statuses is None:
            return False
        statuses[node["id"]] = snapshots.row_status(node)
        if not hasattr(self, "dirty"):
            self.dirty = set()
        self.dirty.add(node["robot"])
        if self.flusher is None or self.flusher.done():
            self.flusher = asyncio.ensure_future(self.send_summaries())
        return True

    async def receive(self, text_data: str | None = None, bytes_data: bytes | None = None) -> None:
        """``{"open": [robot names], "resync": bool}`` from fleet.js: the robots the page shows
        opened. A robot just opened gets its rows again from here (the page fetched them before
        the socket knew: a change in between would be lost); on (re)connect (``resync``) a robot
        shown otherwise than the page wants is sent whole."""
        try:
            message = json.loads(text_data or "")
            wanted = {str(name) for name in message["open"][:100]}
            resync = bool(message.get("resync"))
        except (ValueError, KeyError, TypeError, AttributeError):
            return
        changes = [(name, name not in wanted) for name in self.collapsible
                   if (name not in wanted) != (name in self.collapsed)]
        if changes:
            html, statuses = await database_sync_to_async(self.toggle, thread_sensitive=False)(changes, resync)
            for name, collapse in changes:
                if collapse:
                    self.collapsed[name] = statuses[name]
                else:
                    self.collapsed.pop(name, None)
            if html.strip():
                await self.send(text_data=html)

    def toggle(self, changes: list[tuple[str, bool]], whole: bool) -> tuple[str, dict[str, dict[str, str]]]:
        parts, statuses = [], {}
        with script_prefix(self.prefix):
            for name, collapse in changes:
                found = snapshots.robot_section(name, not collapse)
                if found is None:
                    statuses[name] = {}
                    continue
                robot, rows = found
                statuses[name] = getattr(robot, "statuses", {})
                self.known.update(row["id"] for row in rows)
                context = {"robot": robot, "nodes": rows, "can_operate": self.can_operate}
                if whole:
                    parts.append(render_to_string("dashboard/_robot.html", context))
                elif rows:
                    parts.append(render_to_string("dashboard/_node_row.html", {**context, "oob": "true"}))
        return "".join(parts), statuses

    async def send_summaries(self) -> None:
        """The counts of the collapsed robots whose nodes changed since the last time (a
        bring-up of 100 nodes is a few messages, not 200)."""
        await asyncio.sleep(self.SUMMARY_DELAY_S)
        dirty, self.dirty = self.dirty, set()
        parts = [render_to_string("dashboard/_robot_summary.html", {
            "robot": {"name": name}, "summary": snapshots.summary(self.collapsed[name].values()), "oob": True})
            for name in sorted(dirty) if name in self.collapsed]
        if parts:
            await self.send(text_data="".join(parts))

    async def disconnect(self, code: int) -> None:
        flusher = getattr(self, "flusher", None)
        if flusher is not None:
            flusher.cancel()
        await super().disconnect(code)
