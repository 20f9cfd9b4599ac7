"""What the site and its gateways say to each other through Redis. No rclpy, no Django.

Every gateway has a name (``local`` on one machine) and its own Redis keys, all under
``{prefix}:gw:{name}:`` so that one ACL pattern grants a gateway exactly its own:

``commands``  list    site LPUSHes ``{"command", "request_id", "deadline", ...}``; the
                      gateway BRPOPs, drops what is past its deadline (a gateway that comes
                      back never replays stale requests) and answers on ``reply:{request_id}``
``reply:ID``  list    gateway LPUSHes ``{"request_id", "ok", ...}`` (a failure carries
                      ``error: {"code", "message"}``), expiring after REPLY_TTL_S
``facts``     stream  gateway XADDs facts (below), trimmed at FACTS_MAXLEN; the site's
                      ingest process reads it with a consumer group and XACKs after its
                      database commit
``logs``      stream  batches of /rosout records, trimmed at LOGS_MAXLEN, read the same way
``beat``      string  the gateway's heartbeat (JSON, see ``beat``), rewritten every few seconds
``config``    string  written by the site: the robots this gateway watches (JSON, ``config``)
``lease``     string  held by the running instance, so two processes never act as one gateway

Live updates to browsers go straight from the gateway to Channels groups (the site's
consumers turn ``node.state`` into ``node_state``): ``node.state``, ``node.parameters`` and
``run.progress``. Log lines and audit records reach pages from the ingest process, after
they are stored, so that they carry their database ids.
"""
from __future__ import annotations

import json
import re
import uuid
from typing import Any

FLEET_GROUP = "fleet"
GATEWAY_NAME_PATTERN = r"[a-z0-9][a-z0-9_-]{0,62}"
GATEWAY_NAME_RE = re.compile(rf"^{GATEWAY_NAME_PATTERN}$")
DEFAULT_GATEWAY = "local"
INGEST_GROUP = "ingest"

# Bounds. Commands queued per gateway, and how long an unread reply lives.
COMMAND_QUEUE_LIMIT = 1000
REPLY_TTL_S = 60
# Facts kept in Redis for the ingest process (approximate trimming, ``XADD MAXLEN ~``): at a
# few hundred bytes each, tens of MB at most; hours of state changes of a large cell.
FACTS_MAXLEN = 100_000
# Log batches (each up to LOG_BATCH records) kept for the ingest process.
LOGS_MAXLEN = 1_000
LOG_BATCH = 200
# What a gateway holds in memory while Redis is unreachable, before it drops (and counts).
OUTBOX_FACTS_LIMIT = 50_000
OUTBOX_LOG_BATCHES_LIMIT = 500

# Commands a gateway serves.
GET_STATE = "get_state"
GET_AVAILABLE_STATES = "get_available_states"
GET_AVAILABLE_TRANSITIONS = "get_available_transitions"
GET_TRANSITION_GRAPH = "get_transition_graph"
CHANGE_STATE = "change_state"
GET_PARAMETERS = "get_parameters"
SET_PARAMETERS = "set_parameters"
START_RUN = "start_run"
PING = "ping"

# Facts a gateway reports (the ``type`` of each; fields as in the docstrings of the
# builders below and in docs/architecture.md).
NODE_SEEN = "node.seen"  # robot, node
NODE_GONE = "node.gone"  # robot, node
NODE_STATE = "node.state"  # robot, node, state_id
ROBOT_NODES = "robot.nodes"  # robot, nodes: every node of the robot running now
TRANSITION = "transition"  # one audit record of a lifecycle transition (or attempt)
PARAMETER = "parameter"  # one audit record of a parameter change (or attempt)
RUN = "run"  # a group run's spec (for runs the gateway starts) and its progress or end
GATEWAY_STARTED = "gateway.started"  # a new instance: runs it does not know are over


def gateway_key(prefix: str, gateway: str, what: str) -> str:
    return f"{prefix}:gw:{gateway}:{what}"


def gateway_keys_pattern(prefix: str, gateway: str) -> str:
    """Every key of one gateway (for its Redis ACL)."""
    return f"{prefix}:gw:{gateway}:*"


def command_queue(prefix: str, gateway: str) -> str:
    return gateway_key(prefix, gateway, "commands")


def reply_key(prefix: str, gateway: str, request_id: str) -> str:
    return gateway_key(prefix, gateway, f"reply:{request_id}")


def facts_stream(prefix: str, gateway: str) -> str:
    return gateway_key(prefix, gateway, "facts")


def logs_stream(prefix: str, gateway: str) -> str:
    return gateway_key(prefix, gateway, "logs")


def beat_key(prefix: str, gateway: str) -> str:
    return gateway_key(prefix, gateway, "beat")


def config_key(prefix: str, gateway: str) -> str:
    return gateway_key(prefix, gateway, "config")


def lease_key(prefix: str, gateway: str) -> str:
    return gateway_key(prefix, gateway, "lease")


def client_name(gateway: str, instance: str) -> str:
    """The name a gateway instance gives its Redis connections (CLIENT SETNAME), so that the
    site sees at once when its process has ended: its connections close with it."""
    return f"lcm-gw:{gateway}:{instance}"


def channel_layer_key_patterns(prefix: str) -> list[str]:
    """Keys channels-redis touches when a gateway sends to a group (group sets, and the
    browsers' channel queues they list)."""
    return [f"{prefix}:group:*", f"{prefix}specific.*"]


def new_id() -> str:
    return uuid.uuid4().hex


def encode(data: dict) -> str:
    """JSON as both sides write it: NaN and infinities (not JSON) become their text."""
    return json.dumps(finite(data), separators=(",", ":"), allow_nan=False, default=str)


def finite(value: Any) -> Any:
    """``value`` with every non-finite float replaced by its text (``"nan"``, ``"inf"``)."""
    if isinstance(value, float) and value != value or value in (float("inf"), float("-inf")):
        return str(value)
    if isinstance(value, list):
        return [finite(v) for v in value]
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    return value


def robot_group(robot_id: int) -> str:
    return f"robot.{robot_id}"


def node_group(node_key: str) -> str:
    """Group of one node; Channels allows only [a-zA-Z0-9._-] and < 100 characters."""
    safe = re.sub(r"[^a-zA-Z0-9._-]", "_", node_key)
    return f"node.{safe}"[:99]


def node_key(robot_name: str, node_name: str) -> str:
    """Stable, URL-safe id of a node: ``agv-1.joy_to_vel``, ``agv-1.arm.gripper``.

    ROS names never contain dots and robot names are slugs, so the mapping is unambiguous.
    """
    return f"{robot_name}.{node_name.strip('/').replace('/', '.')}"


def node_payload(
    *, key: str, robot: str, name: str, state_id: int, alive: bool, last_seen: str | None, gone_reason: str = ""
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
        "gone_reason": "" if alive else gone_reason,  # "unreachable": its process stopped answering
        "last_seen": last_seen,
    }
