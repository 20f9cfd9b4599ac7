"""The node page's socket (HTML fragments, as the fleet page's: consumers.py) and the log
console's (JSON)."""
from __future__ import annotations

import json
import time
from datetime import datetime

from channels.db import database_sync_to_async
from django.template.loader import render_to_string

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.dashboard import fragments, snapshots
from lifecycle_site.dashboard.consumers import LiveConsumer, RunPanels
from lifecycle_site.ingest import outages
from lifecycle_site.prefix import script_prefix
from ros_gateway.shared import protocol


def last_record(key: str) -> dict | None:
    """The node's latest audit record (its last outcome, with the node's own reason)."""
    record = TransitionRecord.objects.select_related("node").filter(node__key=key).first()
    return record.as_dict() if record else None


class NodeConsumer(RunPanels, LiveConsumer):
    async def prepare(self) -> bool:
        self.key = self.scope["url_route"]["kwargs"]["key"]
        self.groups_to_join = [protocol.node_group(self.key)]
        found = await database_sync_to_async(snapshots.node_robot_and_name)(self.key)
        if found is None:
            return False
        self.robot_id, self.node_name = found
        return True

    def runs_in(self, run: dict) -> str:
        return "node-run"

    def run_scope(self) -> tuple[int | None, str | None]:
        return self.robot_id, self.node_name

    def gateway_views(self) -> list[dict]:
        return snapshots.node_gateway(self.key)

    async def send_snapshot(self) -> None:
        """The node as stored. It clears only the results the page showed before its socket
        opened: a click made while the socket opened may have been answered before this was read
        (the live update of its new state comes right after this: the consumer's messages wait)."""
        node = await database_sync_to_async(snapshots.one_node)(self.key)
        await self.show_state(node, snapshot=True)
        last = await database_sync_to_async(last_record, thread_sensitive=False)(self.key)
        await self.send_last(last)

    gateway_offline = ""  # the node's gateway's name while it is offline
    gateway_known_at: str | None = None  # and its last heartbeat: the states shown are as of then
    header_shown: tuple | None = None  # what the header says of the gateway
    last_shown: tuple = ("", 0)  # (requested_at, id) of the last outcome shown

    async def send_gateway_status(self, offline: list[dict]) -> None:
        """Besides the banner: while the gateway is offline the panel offers no command."""
        await super().send_gateway_status(offline)
        now_offline = offline[0]["name"] if offline else ""
        known_at = offline[0].get("last_beat") if offline else None
        if (now_offline, known_at) != (self.gateway_offline, self.gateway_known_at):
            self.gateway_offline, self.gateway_known_at = now_offline, known_at
            await self.send_snapshot()

    async def gateways_seen(self, views: list[dict]) -> None:
        """The header's word on the gateway follows it (a green "online" under a red banner was untrue)."""
        for view in views[:1]:
            shown = (view["name"], view["online"], view["status"])
            if shown != self.header_shown:
                self.header_shown = shown
                await self.send_html("dashboard/_node_gateway.html", {"gateway": view, "oob": True})

    async def node_state(self, event: dict) -> None:
        await self.show_state(event["node"])

    async def show_state(self, node: dict, snapshot: bool = False) -> None:
        def render() -> str:
            panel = snapshots.state_panel(node, self.gateway_offline, self.gateway_known_at)
            context = {**panel, "can_operate": self.can_operate, "oob": True, "snapshot": snapshot}
            with script_prefix(self.prefix):
                return render_to_string("dashboard/_node_state.html", context) + render_to_string(
                    "dashboard/_node_restart.html", context)

        key = ("node-state", self.prefix, self.can_operate, self.gateway_offline, self.gateway_known_at, snapshot,
               node)
        await self.send(text_data=fragments.rendered(key, render))

    async def audit_record(self, event: dict) -> None:
        await self.send_html("dashboard/_audit_row_oob.html", {"record": event["record"]})
        await self.send_last(event["record"])

    async def send_last(self, record: dict | None) -> None:
        """The last outcome, unless a later record is shown already (records may come out of
        order: one that explains a state change is stored after the change it explains)."""
        order = (record["requested_at"], record["id"]) if record else ("", 0)
        if record is not None and order < self.last_shown:
            return
        self.last_shown = order
        await self.send_html("dashboard/_node_last.html", {"last": record, "oob": True})

    async def node_parameters(self, event: dict) -> None:
        """Values changed by anyone: the 'current value' cells follow."""
        await self.send_html("dashboard/_parameter_values_oob.html", {"changes": event["changes"]})


GAP_WAIT_S = 30.0  # how long after its gateway is back a console looks for the outage's record


class LogConsumer(LiveConsumer):
    """``ws/logs/node/<key>/`` or ``ws/logs/robot/<name>/``: records as JSON; and the stretches
    of /rosout not received while the gateway's process was down (ingest/outages.py), once the
    ingest process has recorded them."""

    gap_since: str | None = None  # the last heartbeat before the gateway went offline
    gap_until = 0.0  # (monotonic) when to stop looking for its record

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
        if offline:
            self.gap_since, self.gap_until = offline[0].get("last_beat"), 0.0
        elif self.gap_since is not None:
            self.gap_until = time.monotonic() + GAP_WAIT_S

    async def gateways_seen(self, views: list[dict]) -> None:
        """Back after an outage: the stretch not received, once it is on record."""
        if self.gap_since is None or not self.gap_until or not views or not views[0]["online"]:
            return
        found = await database_sync_to_async(self.gaps, thread_sensitive=False)(views[0]["name"])
        if found or time.monotonic() > self.gap_until:
            self.gap_since, self.gap_until = None, 0.0
        if found:
            await self.send(text_data=json.dumps({"gaps": found}))

    def gaps(self, gateway: str) -> list[dict]:
        """Its outages since then that have ended (the ingest process closes one within seconds of
        the gateway's return: until then it is looked for again)."""
        found = outages.recent(gateway, datetime.fromisoformat(self.gap_since)) if self.gap_since else []
        return [gap for gap in found if gap["ended"]]
