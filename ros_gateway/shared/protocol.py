"""What the site and the gateway say to each other through Redis.

No rclpy here: the web process imports this module.

Commands are request/reply with a bounded wait, so they use two plain Redis lists rather
than the channel layer (whose process-local reply channels are tied to one event loop,
while Django's sync views and tests run each request on a loop of its own):
the site LPUSHes ``{"command": NAME, "request_id": ID, "deadline": EPOCH_S, ...arguments}``
onto command_queue(); the gateway BRPOPs it, drops it if the deadline has passed (so a
gateway that comes back never replays stale requests), and LPUSHes its reply
``{"request_id": ID, "ok": bool, ...}`` (a failed reply carries ``error: {"code", "message"}``)
onto reply_key(ID), which expires soon after.

Updates: the gateway sends ``{"type": "node.state" | "node.logs" | "robot.status", ...}`` to
the groups below; Channels consumers turn the dots into handler names (node_state, ...).
"""
from __future__ import annotations

import re

FLEET_GROUP = "fleet"
# Bounds: queued commands kept at most, and how long an unread reply lives.
COMMAND_QUEUE_LIMIT = 1000
REPLY_TTL_S = 60


def command_queue(prefix: str) -> str:
    return f"{prefix}:gateway:commands"


def reply_key(prefix: str, request_id: str) -> str:
    return f"{prefix}:gateway:reply:{request_id}"

# Commands the gateway serves.
GET_STATE = "get_state"
GET_AVAILABLE_STATES = "get_available_states"
GET_AVAILABLE_TRANSITIONS = "get_available_transitions"
GET_TRANSITION_GRAPH = "get_transition_graph"
CHANGE_STATE = "change_state"
GET_PARAMETERS = "get_parameters"
SET_PARAMETERS = "set_parameters"
START_RUN = "start_run"
PING = "ping"


def robot_group(robot_id: int) -> str:
    return f"robot.{robot_id}"


def node_group(node_key: str) -> str:
    """Group of one node; Channels allows only [a-zA-Z0-9._-] and < 100 characters."""
    safe = re.sub(r"[^a-zA-Z0-9._-]", "_", node_key)
    return f"node.{safe}"[:99]


def node_payload(
    *, key: str, robot: str, name: str, state_id: int, alive: bool, last_seen: str | None
) -> dict:
    """How a node is described to the API and to live pages, from the DB or the gateway."""
    from ros_gateway.shared import state_machine as sm

    return {
        "id": key,
        "robot": robot,
        "name": name,
        "state": sm.state_dict(state_id),
        "transitions": [t.as_dict() for t in sm.valid_transitions(state_id)] if alive else [],
        "alive": alive,
        "last_seen": last_seen,
    }
