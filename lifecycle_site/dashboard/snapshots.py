"""Plain-data snapshots that pages and consumers render (one query each, no N+1)."""
from __future__ import annotations

import os
from datetime import datetime, timezone
from functools import lru_cache
from typing import Collection, Iterable
from urllib.parse import quote

from django.core.cache import cache
from django.template.loader import render_to_string
from django.urls import reverse
from django.utils.http import RFC3986_SUBDELIMS
from django.utils.safestring import mark_safe
from django.utils.translation import get_language
from django.utils.translation import gettext as _

from lifecycle_site.dashboard.graph import layout
from lifecycle_site.dashboard.runs import recent_runs
from lifecycle_site.fleet.models import Gateway, ManagedNode, Robot
from lifecycle_site.fleet.serializers import node_dict
from lifecycle_site.gateway_link import gateways
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm

# Primary states first, then the transition states, as the node's get_available_states lists them.
STATES = [sm.state_dict(s) for s in sm.PRIMARY_STATES] + [
    sm.state_dict(s) for s in sm.STATE_LABELS if not sm.is_primary(s) and s != sm.UNKNOWN
]


# Stands in for a node key while a URL is reversed once (no key, prefix or route holds it).
_KEY = "@node-key@"
# What reverse() leaves unquoted in a URL (django.urls.resolvers), so keys come out the same.
_URL_SAFE = RFC3986_SUBDELIMS + "/~:@"


def with_links(nodes: Iterable[dict]) -> None:
    """Put each node's page and transition URLs into its dict, as ``url`` and
    ``transition_url`` (and ``watch_url`` for a name not seen yet), for the fleet row
    (dashboard/_node_row.html).

    Each route is reversed once, under the current script prefix (so sub-path serving keeps
    working), and the quoted key is put in per node: a fleet of 300 nodes needs about a
    thousand URLs, and a reverse() each was half the time of rendering it."""
    page_head, _, page_tail = reverse("dashboard:node", args=[_KEY]).rpartition(_KEY)
    post_head, _, post_tail = reverse("dashboard:node-transition", args=[_KEY]).rpartition(_KEY)
    watch_urls: dict[str, str] = {}
    for node in nodes:
        key = quote(node["id"], safe=_URL_SAFE)
        node["url"] = page_head + key + page_tail
        node["transition_url"] = post_head + key + post_tail
        robot = node.get("robot")
        if robot and node.get("last_seen") is None:  # a watched name not seen yet: it can be unwatched
            if robot not in watch_urls:
                watch_urls[robot] = reverse("dashboard:watch-node", args=[robot])
            node["watch_url"] = watch_urls[robot]


def fleet_row(node: dict) -> dict:
    """A node as the fleet row renders it: a copy with its URLs (for a pushed update)."""
    row = dict(node)
    with_links([row])
    return row


# A fleet of more than FLEET_ROWS_MAX nodes shows each robot of more than ROBOT_ROWS_MAX nodes
# collapsed (its counts by state) until it is opened; the page keeps the opened ones in its
# URL (?open=a,b). Rendering 1,000 rows took most of the page's time. Both sizes can be set in
# the site's environment (LIFECYCLE_FLEET_COLLAPSE_ABOVE, LIFECYCLE_ROBOT_COLLAPSE_ABOVE).
FLEET_ROWS_MAX = int(os.environ.get("LIFECYCLE_FLEET_COLLAPSE_ABOVE", "300"))
ROBOT_ROWS_MAX = int(os.environ.get("LIFECYCLE_ROBOT_COLLAPSE_ABOVE", "25"))
FIND_MAX = 50  # matches the name filter lists from collapsed robots
# One tuple per node, enough for a row (node_payload) or a collapsed robot's counts.
NODE_FIELDS = ("robot_id", "key", "name", "state_id", "alive", "gone_reason", "last_seen")
# A row's data-status for the states a transition is under way in (fleet.js counts them so).
BUSY = {sm.state_label(s) for s in sm.STATE_LABELS if not sm.is_primary(s) and s != sm.UNKNOWN}
# The order fleet.js lists counts in.
COUNT_ORDER = ["active", "inactive", "unconfigured", "finalized", "busy", "lost", "waiting"]


def status_of(alive: bool, label: str, seen: bool, gone_reason: str) -> str:
    """A row's data-status (templatetags node_status, transition states as 'busy')."""
    if alive:
        return "busy" if label in BUSY else label
    if not seen:
        return "waiting"
    return "unreachable" if gone_reason == "unreachable" else "lost"


def row_status(node: dict) -> str:
    return status_of(node["alive"], node["state"]["label"], node.get("last_seen") is not None,
                     node.get("gone_reason", ""))


def _tuple_status(t: tuple) -> str:
    _, _, _, state_id, alive, gone_reason, last_seen = t
    return status_of(alive, sm.state_label(state_id), last_seen is not None, gone_reason)


def _tuple_payload(t: tuple, robot: str) -> dict:
    _, key, name, state_id, alive, gone_reason, last_seen = t
    return protocol.node_payload(key=key, robot=robot, name=name, state_id=state_id, alive=alive,
                                 gone_reason=gone_reason, last_seen=last_seen.isoformat() if last_seen else None)


def summary(statuses: Iterable[str]) -> dict:
    """A collapsed robot's counts: ``{"counts": [(status, n)], "total": n, "alive": n}``."""
    counts: dict[str, int] = {}
    for status in statuses:
        counts[status] = counts.get(status, 0) + 1
    order = COUNT_ORDER + sorted(set(counts) - set(COUNT_ORDER))
    alive = sum(n for s, n in counts.items() if s not in ("lost", "waiting", "unreachable"))
    return {"counts": [(s, counts[s]) for s in order if counts.get(s)], "total": sum(counts.values()),
            "alive": alive}


def fleet(open_robots: Collection[str] = ()) -> list[dict]:
    """Every gateway (those without robots only once they have reported) with its status and
    its robots, each robot with its nodes as plain data, URLs included: three queries and one
    Redis round trip whatever the fleet size. Call it under the script prefix the links are for.

    A robot collapsed (see FLEET_ROWS_MAX; not in ``open_robots``) comes without rows: it has
    ``collapsed``, ``statuses`` (node key -> row status) and ``summary`` (summary()).
    ``collapsible`` says whether it is collapsed unless opened.

    Each item: ``{"gateway": gateways.describe(...), "robots": [(robot, [node dicts])]}``."""
    rows = list(Gateway.objects.order_by("name"))
    robots = list(Robot.objects.order_by("name"))
    raw: dict[int, list[tuple]] = {r.id: [] for r in robots}
    for t in ManagedNode.objects.order_by("name").values_list(*NODE_FIELDS):
        raw[t[0]].append(t)
    crowded = sum(len(nodes) for nodes in raw.values()) > FLEET_ROWS_MAX
    by_robot: dict[int, list[dict]] = {}
    nodes = []
    for robot in robots:
        robot.collapsible = crowded and len(raw[robot.id]) > ROBOT_ROWS_MAX
        robot.collapsed = robot.collapsible and robot.name not in open_robots
        if robot.collapsed:
            robot.statuses = {t[1]: _tuple_status(t) for t in raw[robot.id]}
            robot.summary = summary(robot.statuses.values())
            by_robot[robot.id] = []
        else:
            by_robot[robot.id] = [_tuple_payload(t, robot.name) for t in raw[robot.id]]
            nodes.extend(by_robot[robot.id])
    with_links(nodes)
    by_gateway: dict[int, list[Robot]] = {}
    for robot in robots:
        by_gateway.setdefault(robot.gateway_id, []).append(robot)
    groups = []
    runs = recent_runs()
    for row, state in zip(rows, gateways.statuses(rows), strict=True):
        mine = by_gateway.get(row.id, [])
        if mine or state.beat or row.last_beat:
            view = gateways.describe(row, state, [r.name for r in mine])
            for robot in mine:
                robot.recent_runs = runs.get(robot.name, [])
                robot.gateway_view = view
                mark_gateway(by_robot[robot.id], view)
            groups.append({"gateway": view, "robots": [(robot, by_robot[robot.id]) for robot in mine]})
    return groups


def robot_section(name: str, opened: bool) -> tuple[Robot, list[dict]] | None:
    """One robot as fleet() gives it, opened or collapsed (None if there is no such robot)."""
    robot = Robot.objects.select_related("gateway").filter(name=name).first()
    if robot is None:
        return None
    raw = list(ManagedNode.objects.filter(robot=robot).order_by("name").values_list(*NODE_FIELDS))
    view = gateway_of(robot)
    robot.gateway_view = view
    robot.recent_runs = recent_runs(robot.id).get(robot.name, [])
    robot.collapsible = True  # asked for by its button, which only collapsible robots have
    robot.collapsed = not opened
    if robot.collapsed:
        robot.statuses = {t[1]: _tuple_status(t) for t in raw}
        robot.summary = summary(robot.statuses.values())
        return robot, []
    rows = [_tuple_payload(t, robot.name) for t in raw]
    with_links(rows)
    mark_gateway(rows, view)
    return robot, rows


def robot_statuses(name: str) -> dict[str, str]:
    """Node key -> row status of one robot's nodes (for a socket that shows it collapsed)."""
    return {t[1]: _tuple_status(t) for t in
            ManagedNode.objects.filter(robot__name=name).values_list(*NODE_FIELDS)}


def find(query: str, state: str, robot_names: list[str], keys: Collection[str] | None = None
         ) -> tuple[list[dict], int]:
    """Nodes of these (collapsed) robots whose name holds ``query`` and whose row status is
    ``state`` (either may be empty; "attention": whose key is in ``keys``): the first FIND_MAX by
    robot and name, with links, and how many matched in all."""
    rows = ManagedNode.objects.filter(robot__name__in=robot_names)
    if query:
        rows = rows.filter(name__icontains=query)
    found: list[dict] = []
    count = 0
    for t in rows.order_by("robot__name", "name").values_list(*NODE_FIELDS, "robot__name"):
        if state == "attention":
            if t[1] not in (keys or ()):
                continue
        elif state and _tuple_status(t[:-1]) != state:
            continue
        count += 1
        if len(found) < FIND_MAX:
            found.append(_tuple_payload(t[:-1], t[-1]))
    with_links(found)
    return found, count


def mark_gateway(rows: Iterable[dict], view: dict) -> None:
    """What a node row needs of its robot's gateway: while it is offline the row shows the
    states as last known (as of its last heartbeat) and offers no command."""
    for row in rows:
        row["gateway"] = view["name"]
        row["gateway_offline"] = not view["online"]
        row["known_at"] = view.get("last_beat")


# Every open page's socket asks for its gateways every few seconds (consumers.watch_gateway):
# answers are kept this long in the process's memory, so fifty screens cost one read. Kept per
# language: a gateway's reason is in words (gateways.describe(), in the active language).
GATEWAY_VIEWS_TTL_S = 1.0


def gateway_views() -> list[dict]:
    """What fleet() says of the gateways, without the nodes (for the fleet page's watch)."""
    return cache.get_or_set(f"socket-gateway-views:{get_language()}", _gateway_views, GATEWAY_VIEWS_TTL_S)


def _gateway_views() -> list[dict]:
    rows = list(Gateway.objects.order_by("name"))
    names: dict[int, list[str]] = {}
    for gateway_id, name in Robot.objects.order_by("name").values_list("gateway_id", "name"):
        names.setdefault(gateway_id, []).append(name)
    return [
        gateways.describe(row, state, names.get(row.id, []))
        for row, state in zip(rows, gateways.statuses(rows), strict=True)
        if names.get(row.id) or state.beat or row.last_beat
    ]


def node_gateway(key: str) -> list[dict]:
    """The gateway of a node's robot, as a one-item list (empty if the node is gone)."""
    def read() -> list[dict]:
        node = ManagedNode.objects.select_related("robot__gateway").filter(key=key).first()
        return [gateway_of(node.robot)] if node else []

    return cache.get_or_set(f"socket-node-gateway:{get_language()}:{key}", read, GATEWAY_VIEWS_TTL_S)


def robot_gateway(name: str) -> list[dict]:
    def read() -> list[dict]:
        robot = Robot.objects.select_related("gateway").filter(name=name).first()
        return [gateway_of(robot)] if robot else []

    return cache.get_or_set(f"socket-robot-gateway:{get_language()}:{name}", read, GATEWAY_VIEWS_TTL_S)


def offline(groups: list[dict]) -> list[dict]:
    """The gateways of ``fleet()`` that have robots and take no commands now."""
    return [g["gateway"] for g in groups if g["robots"] and not g["gateway"]["online"]]


def gateway_of(robot: Robot) -> dict:
    """A robot's gateway as pages show it (``robot.gateway`` select_related, ideally)."""
    return gateways.describe(robot.gateway, gateways.status(robot.gateway), [robot.name])


def node_exists(key: str) -> bool:
    return ManagedNode.objects.filter(key=key).exists()


def node_robot_and_name(key: str) -> tuple[int, str] | None:
    """The node's robot id and its name, or None if there is no such node."""
    return ManagedNode.objects.filter(key=key).values_list("robot_id", "name").first()


def robot_rows(robot_names: list[str], view: dict) -> list[dict]:
    """The fleet rows of these robots' nodes, marked with their gateway's state (``view``)."""
    rows = [node_dict(node) for node in
            ManagedNode.objects.select_related("robot").filter(robot__name__in=robot_names).order_by("name")]
    with_links(rows)
    mark_gateway(rows, view)
    return rows


def one_node(key: str) -> dict:
    return node_with_since(ManagedNode.objects.select_related("robot").get(key=key))


def node_with_since(node: ManagedNode) -> dict:
    """The node as pages show it, with when it entered its state (``state_changed``): a
    transition under way counts its time from there, also on a page opened during it."""
    payload = node_dict(node)
    payload["state_changed"] = node.state_changed.isoformat() if node.state_changed else None
    return payload


def graph_svg(state_id: int, alive: bool) -> str:
    """The state machine drawing; a handful of variants, each rendered once per language (it
    is the costly part of a node page's live update)."""
    return _graph_svg(state_id, alive, get_language())


@lru_cache(maxsize=64)
def _graph_svg(state_id: int, alive: bool, language: str | None) -> str:
    context = {"graph": layout(state_id, alive), "node": {"state": sm.state_dict(state_id)}}
    return mark_safe(render_to_string("dashboard/_graph.html", context))  # (in ``language``, the active one)


def state_panel(node: dict, gateway_offline: str = "", known_at: str | None = None) -> dict:
    """Context of the node page's live part: state, valid transitions, graph, whether a
    restart can work. ``gateway_offline``: the name of the node's gateway while it is offline
    (the state shown is then the last known one, as of ``known_at``, its last heartbeat, and
    no command can be sent)."""
    refusal = restart_refusal(node)
    if gateway_offline and not refusal:
        refusal = _("The gateway %(gateway)s is offline: no command can be sent until it is back.") % {
            "gateway": gateway_offline}
    return {
        "node": node,
        "graph_svg": graph_svg(node["state"]["id"], node["alive"]),
        "busy": node["alive"] and not sm.is_primary(node["state"]["id"]),
        "states": STATES,
        "gateway_offline": gateway_offline,
        "known_at": known_at if gateway_offline else None,
        "restart_refusal": refusal,
        # How long a transition has been under way (live.js, data-elapsed-from): from when the
        # node entered its state as stored, else from now (a push: it entered it just now).
        "state_since": node.get("state_changed") or datetime.now(timezone.utc).isoformat(),
    }


def restart_refusal(node: dict) -> str:
    """Why a restart cannot work now ('' if it can): it drives the node's lifecycle, which a
    finalized node (or one that is not running) no longer has."""
    values = {"node": node["name"]}
    if node.get("last_seen") is None and not node["alive"]:
        return _("%(node)s has not appeared yet: there is nothing to restart.") % values
    if not node["alive"]:
        return _("%(node)s is not running: its process must be started again "
                 "(a restart needs a running node).") % values
    if node["state"]["id"] == sm.FINALIZED:
        return _("%(node)s is finalized: a lifecycle restart cannot bring it back. Restart its process "
                 "(its supervisor or launch file); with a desired state set, it is then brought back to it.") % values
    return ""


def log_group(scope: str, name: str) -> str | None:
    if scope == "node" and node_exists(name):
        return protocol.node_group(name)
    if scope == "robot":
        robot = Robot.objects.filter(name=name).first()
        return protocol.robot_group(robot.id) if robot else None
    return None
