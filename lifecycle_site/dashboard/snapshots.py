"""Plain-data snapshots that pages and consumers render (one query each, no N+1)."""
from __future__ import annotations

from functools import lru_cache
from typing import Iterable
from urllib.parse import quote

from django.core.cache import cache
from django.template.loader import render_to_string
from django.urls import reverse
from django.utils.http import RFC3986_SUBDELIMS
from django.utils.safestring import mark_safe

from lifecycle_site.dashboard.graph import layout
from lifecycle_site.fleet import gateways
from lifecycle_site.fleet.models import Gateway, ManagedNode, Robot
from lifecycle_site.fleet.serializers import node_dict
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
    ``transition_url``, for the fleet row (dashboard/_node_row.html).

    Each route is reversed once, under the current script prefix (so sub-path serving keeps
    working), and the quoted key is put in per node: a fleet of 300 nodes needs about a
    thousand URLs, and a reverse() each was half the time of rendering it."""
    page_head, _, page_tail = reverse("dashboard:node", args=[_KEY]).rpartition(_KEY)
    post_head, _, post_tail = reverse("dashboard:node-transition", args=[_KEY]).rpartition(_KEY)
    for node in nodes:
        key = quote(node["id"], safe=_URL_SAFE)
        node["url"] = page_head + key + page_tail
        node["transition_url"] = post_head + key + post_tail


def fleet_row(node: dict) -> dict:
    """A node as the fleet row renders it: a copy with its URLs (for a pushed update)."""
    row = dict(node)
    with_links([row])
    return row


def fleet() -> list[dict]:
    """Every gateway (those without robots only once they have reported) with its status and
    its robots, each robot with its nodes as plain data, URLs included: three queries and one
    Redis round trip whatever the fleet size. Call it under the script prefix the links are for.

    Each item: ``{"gateway": gateways.describe(...), "robots": [(robot, [node dicts])]}``."""
    rows = list(Gateway.objects.order_by("name"))
    robots = list(Robot.objects.order_by("name"))
    by_robot: dict[int, list[dict]] = {r.id: [] for r in robots}
    nodes = []
    for node in ManagedNode.objects.select_related("robot").order_by("name"):
        row = node_dict(node)
        by_robot[node.robot_id].append(row)
        nodes.append(row)
    with_links(nodes)
    by_gateway: dict[int, list[Robot]] = {}
    for robot in robots:
        by_gateway.setdefault(robot.gateway_id, []).append(robot)
    groups = []
    for row, state in zip(rows, gateways.statuses(rows), strict=True):
        mine = by_gateway.get(row.id, [])
        if mine or state.beat or row.last_beat:
            groups.append({
                "gateway": gateways.describe(row, state, [r.name for r in mine]),
                "robots": [(robot, by_robot[robot.id]) for robot in mine],
            })
    return groups


# Every open page's socket asks for its gateways every few seconds (consumers.watch_gateway):
# answers are kept this long in the process's memory, so fifty screens cost one read.
GATEWAY_VIEWS_TTL_S = 1.0


def gateway_views() -> list[dict]:
    """What fleet() says of the gateways, without the nodes (for the fleet page's watch)."""
    return cache.get_or_set("socket-gateway-views", _gateway_views, GATEWAY_VIEWS_TTL_S)


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

    return cache.get_or_set(f"socket-node-gateway:{key}", read, GATEWAY_VIEWS_TTL_S)


def robot_gateway(name: str) -> list[dict]:
    def read() -> list[dict]:
        robot = Robot.objects.select_related("gateway").filter(name=name).first()
        return [gateway_of(robot)] if robot else []

    return cache.get_or_set(f"socket-robot-gateway:{name}", read, GATEWAY_VIEWS_TTL_S)


def offline(groups: list[dict]) -> list[dict]:
    """The gateways of ``fleet()`` that have robots and take no commands now."""
    return [g["gateway"] for g in groups if g["robots"] and not g["gateway"]["online"]]


def gateway_of(robot: Robot) -> dict:
    """A robot's gateway as pages show it (``robot.gateway`` select_related, ideally)."""
    return gateways.describe(robot.gateway, gateways.status(robot.gateway), [robot.name])


def node_exists(key: str) -> bool:
    return ManagedNode.objects.filter(key=key).exists()


def one_node(key: str) -> dict:
    return node_dict(ManagedNode.objects.select_related("robot").get(key=key))


@lru_cache(maxsize=64)
def graph_svg(state_id: int, alive: bool) -> str:
    """The state machine drawing; a handful of variants, each rendered once (it is the
    costly part of a node page's live update)."""
    context = {"graph": layout(state_id, alive), "node": {"state": sm.state_dict(state_id)}}
    return mark_safe(render_to_string("dashboard/_graph.html", context))


def state_panel(node: dict) -> dict:
    """Context of the node page's live part: state, valid transitions, graph."""
    return {
        "node": node,
        "graph_svg": graph_svg(node["state"]["id"], node["alive"]),
        "busy": node["alive"] and not sm.is_primary(node["state"]["id"]),
        "states": STATES,
    }


def log_group(scope: str, name: str) -> str | None:
    if scope == "node" and node_exists(name):
        return protocol.node_group(name)
    if scope == "robot":
        robot = Robot.objects.filter(name=name).first()
        return protocol.robot_group(robot.id) if robot else None
    return None
