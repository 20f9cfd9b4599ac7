"""Channels consumers: subscribe a browser to the gateways' groups and forward what matters.
Here the common ground and the fleet page's; the node page's and the log console's are in
node_consumers.py.

Fleet and node pages get HTML fragments that htmx swaps in by id (hx-swap-oob), rendered
from the same partial templates as the first page load. Log consoles get JSON, because
bounding, filtering and pausing a fast stream is the browser's job there.
"""
from __future__ import annotations

import asyncio
import logging
from urllib.parse import parse_qs

from channels.db import database_sync_to_async
from channels.generic.websocket import AsyncWebsocketConsumer
from django.template.loader import render_to_string
from django.utils import translation
from redis.exceptions import RedisError

from lifecycle_site.dashboard import attention, fragments, runs, snapshots, socket_checks
from lifecycle_site.dashboard.collapse import CollapsedRobots
from lifecycle_site.fleet.models import Robot
from lifecycle_site.languages import choice as languages
from lifecycle_site.prefix import forwarded_prefix, script_prefix
from ros_gateway.shared import protocol

log = logging.getLogger(__name__)

OPEN_RUN_CHECK_S = 0.5  # how often a page with an open run looks at its runs (cached 1 s per page kind)
GATEWAY_CHECK_S = 3.0  # also how soon a socket closes after logout, deactivation or role removal
NOT_LOGGED_IN = socket_checks.NOT_LOGGED_IN
NO_ROLE = socket_checks.NO_ROLE
NOT_FOUND = 4404
# The site has lost its link to Redis (down, restarting, not answering): the page reconnects
# on this code by itself, with a growing delay (static/js/live.js, static/js/logs.js). Not
# 1013 ("try again later"): a server may close only with 1000 or 3000-4999 (autobahn, RFC 6455).
TRY_AGAIN_LATER = 4503
LINK_LOST = "The site has lost its link to Redis; reconnecting when it is back."
# How long joining the page's groups may take before the socket is refused (Redis hangs).
LINK_TIMEOUT_S = 5.0
LINK_ERRORS = (RedisError, OSError, asyncio.TimeoutError)


class LiveConsumer(AsyncWebsocketConsumer):
    """Common ground: login required, group membership, upkeep of the banner that names the
    offline gateways of what the page shows."""

    groups_to_join: list[str]
    accepted = False

    async def __call__(self, scope, receive, send) -> None:
        """Without Redis no update can reach the page: the socket is then refused or ended with
        TRY_AGAIN_LATER and a reason, instead of an error (HTTP 500 in the handshake, 1011 after
        it, and a traceback in the log for each socket)."""
        try:
            await super().__call__(scope, receive, send)
        except LINK_ERRORS as exc:
            log.warning("WebSocket %s ended: the channel layer's Redis failed (%s: %s)", scope.get("path"),
                        type(exc).__name__, exc)
            try:
                if not self.accepted:  # accepted to be closed with a code the page understands
                    await send({"type": "websocket.accept"})
                await send({"type": "websocket.close", "code": TRY_AGAIN_LATER, "reason": LINK_LOST})
            except Exception:  # noqa: BLE001 - the browser may be gone already
                pass
        finally:
            watcher = getattr(self, "watcher", None)
            if watcher is not None:
                watcher.cancel()

    async def dispatch(self, message: dict) -> None:
        """A group message this page cannot show is dropped (and logged), never the socket:
        what reaches the groups is checked by the site (ingest/live_relay.py), but one bad
        message must not close every open page."""
        if str(message.get("type", "")).startswith("websocket."):
            await super().dispatch(message)
            return
        try:
            await super().dispatch(message)
        except LINK_ERRORS:
            raise
        except Exception:  # noqa: BLE001
            log.exception("WebSocket %s: dropped a %s message it could not show", self.scope.get("path"),
                          str(message.get("type"))[:40])

    async def accept(self, subprotocol=None, headers=None) -> None:
        await super().accept(subprotocol, headers)
        self.accepted = True

    async def connect(self) -> None:
        # The page's language for everything this socket renders: activated in this connection's
        # own task (a context variable), so it holds for all its messages and their worker threads.
        translation.activate(await database_sync_to_async(languages.of_scope)(self.scope))
        user = self.scope.get("user")
        if user is None or not user.is_authenticated:
            await self.close(code=NOT_LOGGED_IN)
            return
        if not await database_sync_to_async(user.has_perm)("fleet.view_managednode"):
            await self.close(code=NO_ROLE)
            return
        self.can_operate = await database_sync_to_async(user.has_perm)("fleet.operate_node")
        session = self.scope.get("session")
        self.session_key = getattr(session, "session_key", None)
        headers = dict(self.scope.get("headers", []))
        self.prefix = forwarded_prefix(headers.get(b"x-forwarded-prefix", b"").decode("latin-1"))
        if not await self.prepare():
            await self.close(code=NOT_FOUND)
            return
        for group in self.groups_to_join:
            await asyncio.wait_for(self.channel_layer.group_add(group, self.channel_name), LINK_TIMEOUT_S)
        await self.accept()
        self.offline_seen: tuple | None = None
        await self.send_snapshot()
        self.watcher = asyncio.ensure_future(self.watch_gateway())

    async def disconnect(self, code: int) -> None:
        watcher = getattr(self, "watcher", None)
        if watcher is not None:
            watcher.cancel()
        try:
            for group in getattr(self, "groups_to_join", []):
                await asyncio.wait_for(self.channel_layer.group_discard(group, self.channel_name), LINK_TIMEOUT_S)
        except LINK_ERRORS:
            pass  # Redis is down: the membership expires on its own (group_expiry)

    async def prepare(self) -> bool:
        return True

    async def route_robot(self) -> Robot | None:
        """The robot a page's route names (ws/robots/<robot>/...), with its gateway; None if none is."""
        name = self.scope["url_route"]["kwargs"]["robot"]
        return await database_sync_to_async(Robot.objects.select_related("gateway").filter(name=name).first)()

    async def send_snapshot(self) -> None:
        pass

    async def watch_gateway(self) -> None:
        """Tell the page when a gateway of what it shows goes offline or comes back."""
        while True:
            refused = await database_sync_to_async(self.refusal, thread_sensitive=False)()
            if refused:
                await self.close(code=refused)
                return
            views = await database_sync_to_async(self.gateway_views, thread_sensitive=False)()
            offline = [v for v in views if v["robots"] and not v["online"]]
            seen = tuple((v["name"], v["status"], v["last_beat"]) for v in offline)
            if seen != self.offline_seen:
                self.offline_seen = seen
                await self.send_gateway_status(offline)
            await self.gateways_seen(views)
            await self.check_runs()
            await self.pause(GATEWAY_CHECK_S)

    def refusal(self) -> int | None:
        """Whether this socket may still receive updates (socket_checks.check_session, kept a
        second per session), and it is still this socket's user: a close code if not."""
        verdict = socket_checks.check_session(self.session_key)
        if verdict.refusal is None and verdict.user_id != self.scope["user"].pk:
            return NOT_LOGGED_IN
        self.can_operate = verdict.can_operate
        return verdict.refusal

    def gateway_views(self) -> list[dict]:
        """The gateways of what the page shows (gateway_link.gateways.describe() dicts)."""
        return []

    async def gateways_seen(self, views: list[dict]) -> None:
        pass

    async def check_runs(self) -> None:
        pass

    async def pause(self, seconds: float) -> None:
        await asyncio.sleep(seconds)

    async def send_gateway_status(self, offline: list[dict]) -> None:
        await self.send_html("dashboard/_gateway_banner.html", {"offline_gateways": offline, "oob": True})

    async def send_html(self, template: str, context: dict) -> None:
        with script_prefix(self.prefix):
            html = render_to_string(template, context)
        await self.send(text_data=html)

    # Group messages this consumer does not use are ignored rather than raising.
    async def node_logs(self, event: dict) -> None:
        pass

    async def audit_record(self, event: dict) -> None:
        pass

    async def node_parameters(self, event: dict) -> None:
        pass


class RunPanels:
    """The run panels of what a page shows: the gateway's pushes as they come, and every few
    seconds what the database says of the page's runs, so that every run's final state
    arrives (a recovery the gateway started itself, a run made on another screen or by the
    API, a last push that went only to other groups). Each panel goes into the page's run list
    (live.js replaces the one there unless it shows a later state)."""

    run_ranks: dict[str, int]  # how far each run shown has come (runs.run_rank)

    def ranks(self) -> dict[str, int]:
        if not hasattr(self, "run_ranks"):
            self.run_ranks = {}
        return self.run_ranks

    def runs_in(self, run: dict) -> str:
        raise NotImplementedError

    def run_scope(self) -> tuple[int | None, str | None]:
        """(robot id, node name) for runs.recent_runs: None for every robot / node."""
        return None, None

    async def run_progress(self, event: dict) -> None:
        await self.send_run(event["run"])

    async def send_run(self, run: dict) -> None:
        # (a push says nothing of who started the run, when, nor of its robot's order)
        run = await database_sync_to_async(runs.completed, thread_sensitive=False)(run)
        ranks = self.ranks()
        ranks[run["id"]] = max(ranks.get(run["id"], -1), runs.run_rank(run))
        await self.send_html("dashboard/_run.html", {"run": run, "runs_in": self.runs_in(run)})

    async def pause(self, seconds: float) -> None:
        """Until the next gateway check; while a run the page shows is open, its runs are read
        every OPEN_RUN_CHECK_S meanwhile, so that its end shows within about a second."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + seconds
        while (left := deadline - loop.time()) > 0:
            await asyncio.sleep(min(OPEN_RUN_CHECK_S, left))
            await self.between_checks()

    async def between_checks(self) -> None:
        if any(rank < runs.DONE_RANK for rank in self.ranks().values()):
            await self.check_runs()

    async def check_runs(self) -> None:
        shown = await database_sync_to_async(runs.runs_view, thread_sensitive=False)(*self.run_scope())
        ranks = self.ranks()
        for run in shown:  # oldest first: each new one goes first in its list
            if runs.run_rank(run) > ranks.get(run["id"], -1):
                await self.send_run(run)


class AttentionStrip:
    """For FleetConsumer: the "needs attention" strip (attention.py) follows what it lists: read
    at each gateway check (alerts, desired states and audit records come without a push) and,
    for ATTENTION_AFTER_PUSH_S after a node's update, at each of the checks between (its audit
    record is stored a moment after its state was pushed). Sent only when it changed."""

    ATTENTION_AFTER_PUSH_S = 2.5
    attention_sent: dict | None = None  # what the strip shown says (its "N s ago" move in the page)
    attention_until = 0.0  # (loop time) read it at the checks between until then
    prefix: str

    def attention_soon(self) -> None:
        self.attention_until = asyncio.get_running_loop().time() + self.ATTENTION_AFTER_PUSH_S

    async def send_attention(self) -> None:
        data = await database_sync_to_async(attention.current, thread_sensitive=False)()
        if data == self.attention_sent:
            return
        self.attention_sent = data

        def render() -> str:
            with script_prefix(self.prefix):  # (its links carry the prefix)
                return render_to_string("dashboard/_attention.html", {"attention": attention.view(data), "oob": True})

        await self.send(text_data=fragments.rendered(("attention", self.prefix, data), render))


class FleetConsumer(AttentionStrip, CollapsedRobots, RunPanels, LiveConsumer):
    """The fleet page; the robots it shows collapsed get their counts instead of rows (collapse.py)."""

    async def between_checks(self) -> None:
        await super().between_checks()
        if self.attention_until and asyncio.get_running_loop().time() < self.attention_until:
            await self.send_attention()

    groups_to_join = [protocol.FLEET_GROUP]

    def runs_in(self, run: dict) -> str:
        return f"robot-{run['robot']}-run"

    async def send_snapshot(self) -> None:
        """The whole fleet list, so a page that reconnects catches up with what it missed.

        Read and rendered in a worker thread of its own: at 300 nodes that is ~30 ms which,
        on the event loop, every push to every page would wait for (and, in the one thread
        that consumers' database calls share, every other page's connect)."""
        query = parse_qs(self.scope.get("query_string", b"").decode("latin-1"))
        opened = [name for name in ",".join(query.get("open", [])).split(",") if name][:100]
        html, self.known = await database_sync_to_async(self.fleet_html, thread_sensitive=False)(opened)
        await self.send(text_data=html)
        self.attention_sent = None  # (a reconnecting page may show an old one)
        await self.send_attention()

    def fleet_html(self, opened: list[str]) -> tuple[str, set[str]]:
        with script_prefix(self.prefix):
            # (the links it puts in carry the prefix)
            groups = snapshots.fleet(opened) if opened else snapshots.fleet()
            html = render_to_string(
                "dashboard/_robots.html", {"gateways": groups, "can_operate": self.can_operate, "oob": True}
            )
        robots = [robot for g in groups for robot, _ in g["robots"]]
        self.heads = {g["gateway"]["name"]: _head(g["gateway"]) for g in groups}
        self.views = {g["gateway"]["name"]: g["gateway"] for g in groups}
        self.gateway_of = {robot.name: g["gateway"]["name"] for g in groups for robot, _ in g["robots"]}
        self.run_ranks = {run["id"]: runs.run_rank(run) for robot in robots for run in robot.recent_runs}
        self.collapsible = {robot.name for robot in robots if robot.collapsible}
        self.collapsed: dict[str, dict[str, str]] = {r.name: r.statuses for r in robots if r.collapsed}
        return html, {n["id"] for group in groups for _, nodes in group["robots"] for n in nodes}

    def gateway_views(self) -> list[dict]:
        return snapshots.gateway_views()

    async def gateways_seen(self, views: list[dict]) -> None:
        """Each gateway's header follows its health and counters (a new gateway needs a reload);
        the "needs attention" strip its contents."""
        await self.send_attention()
        for view in views:
            head = _head(view)
            self.views[view["name"]] = view
            if view["name"] in self.heads and self.heads[view["name"]] != head:
                went = self.heads[view["name"]]["online"] != head["online"]
                self.heads[view["name"]] = head
                await self.send_html("dashboard/_gateway_head.html", {"gateway": view, "oob": True})
                if went:  # its rows: last known states and no commands, or live again
                    await self.send_rows(view)

    async def send_rows(self, view: dict) -> None:
        shown = [name for name in view["robots"] if name not in self.collapsed]

        def render() -> str:
            with script_prefix(self.prefix):
                rows = snapshots.robot_rows(shown, view)
                return render_to_string("dashboard/_node_row.html",
                                        {"nodes": rows, "oob": "true", "can_operate": self.can_operate})

        html = await database_sync_to_async(render, thread_sensitive=False)() if shown else ""
        if html.strip():
            await self.send(text_data=html)

    async def node_state(self, event: dict) -> None:
        node = event["node"]
        self.attention_soon()
        if self.counted(node):  # its robot is shown collapsed: its counts follow, not its row
            return
        new = node["id"] not in self.known
        self.known.add(node["id"])
        template = "dashboard/_node_row_new.html" if new else "dashboard/_node_row.html"
        view = self.views.get(self.gateway_of.get(node["robot"], ""))

        def render() -> str:
            with script_prefix(self.prefix):
                row = snapshots.fleet_row(node)  # its links carry the prefix
                if view is not None:
                    snapshots.mark_gateway([row], view)
                return render_to_string(template, {"node": row, "nodes": [row], "oob": "true",
                                                   "can_operate": self.can_operate})

        gateway = (view["name"], view["online"], view.get("last_beat")) if view is not None else None
        html = fragments.rendered((template, self.prefix, self.can_operate, gateway, node), render)
        await self.send(text_data=html)


def _head(view: dict) -> dict:
    """What a gateway's header shows, but what moves with the clock (each heartbeat's time,
    '2 min ago'): the header is sent again when something else changed."""
    return {k: v for k, v in view.items() if k not in ("since", "reason", "last_beat")}
