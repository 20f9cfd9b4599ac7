"""Plain-data snapshots that pages and consumers render (one query each, no N+1)."""
from __future__ import annotations

from functools import lru_cache

from django.template.loader import render_to_string
from django.utils.safestring import mark_safe

from lifecycle_site.dashboard.graph import layout
from lifecycle_site.fleet.models import ManagedNode, Robot
from lifecycle_site.fleet.serializers import node_dict
from ros_gateway import protocol
from ros_gateway import state_machine as sm

# Primary states first, then the transition states, as the node's get_available_states lists them.
STATES = [sm.state_dict(s) for s in sm.PRIMARY_STATES] + [
    sm.state_dict(s) for s in sm.STATE_LABELS if not sm.is_primary(s) and s != sm.UNKNOWN
]


def fleet() -> list[tuple[Robot, list[dict]]]:
    """Every robot with its nodes as plain data: two queries whatever the fleet size."""
    robots = list(Robot.objects.order_by("name"))
    by_robot: dict[int, list[dict]] = {r.id: [] for r in robots}
    for node in ManagedNode.objects.select_related("robot").order_by("name"):
        by_robot[node.robot_id].append(node_dict(node))
    return [(robot, by_robot[robot.id]) for robot in robots]


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
