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
                      database commit; entries XADDed together with a command's reply
                      carry the field REPLIED too (the site applies their facts from the reply)
``logs``      stream  batches of /rosout records, trimmed at LOGS_MAXLEN, read the same way
``beat``      string  the gateway's heartbeat (JSON, see ``beat``), rewritten every few seconds
``config``    string  written by the site: the robots this gateway watches (JSON, ``config``)
``lease``     string  held by the running instance, so two processes never act as one gateway
``live``      stream  the gateway's live updates for open pages (``node.state``, ``node.parameters``,
                      ``run.progress``), trimmed at LIVE_MAXLEN; the site's ingest process checks each
                      one and sends it on to the pages' Channels groups
``claim:ID``  string  who decides a command's fate: the gateway SET NXes its instance before it
                      carries the command out; a site that stopped waiting SET NXes ABANDONED.
                      Whoever is first decides, so the site can tell the user plainly whether
                      the command was carried out (see ``not_carried_out``)
``verdict:ID`` string written by the site when it ends a group run the gateway may still be
                      carrying out (``{"status", "message", "at"}``, expiring after VERDICT_TTL_S);
                      the gateway only reads it, before a run's next step after a pause, and
                      stops the run if it is there (a verdict is final)

A gateway is a stranger to the site (it runs on a plant-floor device): its Redis user reaches
exactly the keys above, reads ``config`` and ``verdict:*`` without writing them, and never
touches the Channels layer. Its live updates go to its own ``live`` stream; the site checks
them (robot and node names exactly its own, known states, bounded sizes) and sends them on.
Log lines and audit records reach pages from the ingest process, after they are stored, so
that they carry their database ids.
"""
from __future__ import annotations

import hashlib
import json
import re
import uuid
from typing import Any

FLEET_GROUP = "fleet"
GATEWAY_NAME_PATTERN = r"[a-z0-9][a-z0-9_-]{0,62}"
GATEWAY_NAME_RE = re.compile(rf"^{GATEWAY_NAME_PATTERN}$")
DEFAULT_GATEWAY = "local"
# The Redis the site and a gateway use when REDIS_URL is not set (the one `make demo` starts).
DEFAULT_REDIS_URL = "redis://127.0.0.1:6479/0"
INGEST_GROUP = "ingest"
# The stream field ("1") of facts entries handed over in one round trip with a command's reply.
REPLIED = "r"

# A command makes up to this many ROS calls in a row (a transition: read the state, change it,
# read it again); the site waits that many service timeouts plus a grace for the reply.
CALLS_PER_COMMAND = 3
# Bounds. Commands queued per gateway, and how long an unread reply lives.
COMMAND_QUEUE_LIMIT = 1000
REPLY_TTL_S = 60
# A command's claim outlives the site's longest wait for it (3 x 25 s + grace) with room to spare.
CLAIM_TTL_S = 180
ABANDONED = "abandoned"  # the claim a site that stopped waiting leaves: the command is never carried out
# A run's verdict outlives any run (a node step is bounded to minutes) by far.
VERDICT_TTL_S = 24 * 3600
# Facts kept in Redis for the ingest process (approximate trimming, ``XADD MAXLEN ~``): at a
# few hundred bytes each, tens of MB at most; hours of state changes of a large cell.
FACTS_MAXLEN = 100_000
# Log batches (each up to LOG_BATCH records) kept for the ingest process.
LOGS_MAXLEN = 1_000
LOG_BATCH = 200
# Live updates waiting for the site's relay (it reads them within milliseconds; a relay that is
# down finds only the newest when it is back, which is all a page needs).
LIVE_MAXLEN = 1_000
# The largest entry the site reads from a gateway's streams (the stream field's bytes); a larger
# one is not read, and its gateway is quarantined. Fact fields are bounded far below.
MAX_FACT_BYTES = 256 * 1024
MAX_LOG_BATCH_BYTES = 1024 * 1024
MAX_LIVE_BYTES = 256 * 1024
# What a gateway keeps of its own streams' bytes in Redis, as shares of its quota (the site
# publishes the quota in the gateway's config, ``limits.redis_bytes``): it trims its streams to
# these, so an honest gateway stays within its quota even when the ingest process is stopped. A
# third is left for its replies, claims, heartbeat and lease, the site's keys for it, and Redis's
# own rounding (streams were measured 7 % above their budget).
STREAM_SHARES = {"facts": 0.35, "logs": 0.25, "live": 0.05}
# Redis's own bytes per stream entry beyond its fields (an estimate on the high side).
STREAM_ENTRY_OVERHEAD = 64
DEFAULT_REDIS_QUOTA = 16 * 1024 * 1024  # the site's, when Redis will not tell its maxmemory
# A gateway's until its config names its quota (a start's facts take kilobytes).
START_REDIS_QUOTA = 2 * 1024 * 1024
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
SET_PARAMETERS = "set_parameters"  # values; atomic: true for all or none (a parameter file)
START_RUN = "start_run"
PING = "ping"
# A process of a robot's launch profile (ros_gateway/supervisor.py): robot, process, action.
PROCESS_CONTROL = "process_control"
PROCESS_ACTIONS = ("start", "stop", "restart")
PROCESS_USAGE = "process_usage"  # robot -> the CPU and memory of its processes, measured when asked
# A process is a launch profile's (its name), or a Docker container or systemd unit the gateway
# found running a robot's node (ros_gateway/host_units.py), named so: "docker:NAME", "systemd:UNIT".
SUPERVISORS = ("launch", "docker", "systemd")
HOST_PROCESS_RE = re.compile(r"^(docker|systemd):[A-Za-z0-9_.@:\\-]{1,56}$")

# Facts a gateway reports (the ``type`` of each; fields as in the docstrings of the
# builders below and in docs/architecture.md).
NODE_SEEN = "node.seen"  # robot, node
NODE_GONE = "node.gone"  # robot, node, reason: "" | "unreachable" | PROCESS_LOST
NODE_STATE = "node.state"  # robot, node, state_id
ROBOT_NODES = "robot.nodes"  # robot, nodes: every node of the robot running now
TRANSITION = "transition"  # one audit record of a lifecycle transition (or attempt)
PARAMETER = "parameter"  # one audit record of a parameter change (or attempt)
RUN = "run"  # a group run's spec (for runs the gateway starts) and its progress or end
GATEWAY_STARTED = "gateway.started"  # a new instance: runs it does not know are over
PROCESS = "process"  # one audit record of a supervised process: an action on it, an exit, a respawn
NODE_PROCESS = "node.process"  # robot, node, process: the launch profile whose process runs it ("" none)
# robot, node, message, changes, window_s, last_change: the gateway stopped keeping the node in its
# desired state (another manager keeps moving it); it leaves it alone until an operator resumes.
ENFORCEMENT_STOPPED = "enforcement.stopped"
TOPIC_RATES = "topic.rates"  # robot, rates: [{topic, hz (None: no publisher), window_s}]: measured for the site
MAX_RATE_TOPICS = 32  # per robot
# robot, statuses: [{name, level, message, hardware_id, values: [[key, value]], topic, node, stale, age_s}]
# (what changed, each status at most every DIAGNOSTICS_REFRESH_S unless its level or message changed),
# heard: [names heard again, unchanged], left_out: statuses not kept since the gateway started (over
# MAX_STATUSES): the robots' /diagnostics and /diagnostics_agg (ros_gateway/diagnostics.py).
DIAGNOSTICS = "diagnostics"
DIAGNOSTIC_TOPICS = ("diagnostics", "diagnostics_agg")  # in the robot's namespace
DIAGNOSTIC_LEVELS = {0: "ok", 1: "warn", 2: "error", 3: "stale"}  # diagnostic_msgs/DiagnosticStatus
DEFAULT_DIAGNOSTICS_STALE_S = 5.0  # no update for this long: stale (as diagnostic_aggregator's default)
DIAGNOSTICS_REFRESH_S = 2.0
# Bounds: statuses kept per robot, per fact; text and key/values per status (longer is cut, more left out).
MAX_STATUSES = 1000
MAX_STATUSES_PER_FACT = 100
MAX_STATUS_NAME, MAX_STATUS_MESSAGE, MAX_HARDWARE_ID = 256, 256, 128
MAX_STATUS_VALUES, MAX_VALUE_KEY, MAX_VALUE_TEXT = 32, 64, 256
# A node's policy for its desired state (the site's config, per node): "off"; "alert" (drift raises
# an alert, on the site); "enforce" (the gateway undoes changes by other tools); "paused" (enforce,
# stopped after a fight until an operator resumes it).
KEEP_POLICIES = ("off", "alert", "enforce")
KEEP_PAUSED = "paused"

# A node's process: lost (it ended, or its node left the graph), or replaced by a new instance.
# A node.gone reason, and, with PROCESS_RESTARTED, a transition record's outcome (which also
# moves the node's ``process`` status on the site).
PROCESS_LOST = "process_lost"
PROCESS_RESTARTED = "process_restarted"


def gateway_key(prefix: str, gateway: str, what: str) -> str:
    return f"{prefix}:gw:{gateway}:{what}"


def gateway_keys_pattern(prefix: str, gateway: str) -> str:
    """Every key of one gateway (the site's scans of what it holds)."""
    return f"{prefix}:gw:{gateway}:*"


# The keys a gateway writes (its Redis user may read and write them) and those the site writes
# for it (read only); ``*`` stands for a request or run id. Nothing else is within its reach.
GATEWAY_WRITES = ("commands", "reply:*", "claim:*", "facts", "logs", "live", "beat", "lease")
GATEWAY_READS = ("config", "verdict:*")


def gateway_key_patterns(prefix: str, gateway: str) -> tuple[list[str], list[str]]:
    """(keys the gateway reads and writes, keys it only reads), as Redis ACL key patterns."""
    return ([gateway_key(prefix, gateway, what) for what in GATEWAY_WRITES],
            [gateway_key(prefix, gateway, what) for what in GATEWAY_READS])


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


def live_stream(prefix: str, gateway: str) -> str:
    return gateway_key(prefix, gateway, "live")


def ingest_lease_key(prefix: str) -> str:
    """Held by the one ingest process that does the site-wide work (alert rules, configs, the
    gateways' Redis users); every ingest process reads the streams of the gateways it holds."""
    return f"{prefix}:site:ingest:lease"


def claim_key(prefix: str, gateway: str, request_id: str) -> str:
    return gateway_key(prefix, gateway, f"claim:{request_id}")


def verdict_key(prefix: str, gateway: str, run_id: str) -> str:
    """The site's final word on a run of this gateway (the gateway reads it, never writes it)."""
    return gateway_key(prefix, gateway, f"verdict:{run_id}")


def client_name(gateway: str, instance: str) -> str:
    """The name a gateway instance gives its Redis connections (CLIENT SETNAME), so that the
    site sees at once when its process has ended: its connections close with it."""
    return f"lcm-gw:{gateway}:{instance}"


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


# A parameter value in an audit fact: larger ones are described, not sent (the site keeps no more).
VALUE_BYTES = 16 * 1024


def bounded(value: Any) -> Any:
    """A parameter value for an audit fact: itself, or a note of its size when its JSON is
    larger than VALUE_BYTES (a 100,000-element array would make a fact the site refuses)."""
    size = len(json.dumps(finite(value), default=str))
    return value if size <= VALUE_BYTES else f"(a value of {size} bytes as JSON, not kept: at most {VALUE_BYTES})"


def robot_group(robot_id: int) -> str:
    return f"robot.{robot_id}"


_GROUP_UNSAFE = re.compile(r"[^a-zA-Z0-9._-]")


def node_group(node_key: str) -> str:
    """Group of one node; Channels allows only [a-zA-Z0-9._-] and < 100 characters."""
    return f"node.{_GROUP_UNSAFE.sub('_', node_key)}"[:99]


def node_key(robot_name: str, node_name: str) -> str:
    """Stable, URL-safe id of a node: ``agv-1.joy_to_vel``, ``agv-1.arm.gripper``.

    ROS names never contain dots and robot names are slugs, so the mapping is unambiguous.
    """
    return f"{robot_name}.{node_name.strip('/').replace('/', '.')}"


def node_payload(
    *, key: str, robot: str, name: str, state_id: int, alive: bool, last_seen: str | None, gone_reason: str = "",
    process_status: str = "", process_since: str | None = None,
) -> dict:
    """How a node is described to the API and to live pages, from the DB or the gateway.
    ``process``: what was last seen of its process, ``lost`` or ``restarted`` (a new instance),
    and when; status "" while nothing was."""
    from ros_gateway.shared import state_machine as sm

    status = "" if alive and process_status == "lost" else process_status
    return {
        "id": key,
        "robot": robot,
        "name": name,
        "state": sm.state_dict(state_id),
        "transitions": [t.as_dict() for t in sm.valid_transitions(state_id)] if alive else [],
        "alive": alive,
        "gone_reason": "" if alive else gone_reason,  # "unreachable", or "process_lost"
        "last_seen": last_seen,
        # A node back with the same process after it left the graph is not "lost" any more.
        "process": {"status": status, "since": process_since if status else None},
    }


def not_carried_out(gateway: str, command: dict, reason: str, instance: str, outcome: str = "rejected") -> list[dict]:
    """The audit facts of a command that was not (or not knowingly) carried out: a transition
    record for ``change_state``, one parameter record per name for ``set_parameters``, none for
    what is not audited. Their ids come from the request id, so the site and the gateway may
    both report the same command and it is recorded once. The record carries the time the user
    asked (the command's ``requested_at``) and no completion time, hence no duration: nothing
    ran, or what ran is not known."""
    request_id = str(command.get("request_id") or "")
    kind = command.get("command")
    asked = str(command.get("requested_at") or "")
    if not request_id or not asked or kind not in (CHANGE_STATE, SET_PARAMETERS):
        return []
    common = {"gateway": gateway, "instance": instance, "seq": 0, "at": asked, "robot": command.get("robot"),
              "node": command.get("node"), "source": str(command.get("source") or "api"),
              "user_id": command.get("user_id")}
    if kind == CHANGE_STATE:
        requested = command.get("transition")
        # Not answered (the site gave up after the gateway took it): the gateway's own record of
        # what it did, should it come, has the request's id; this one stands beside it.
        record_id = request_id if outcome != "timed_out" else unanswered_id(request_id)
        return [{**common, **vouching(command), "id": record_id, "type": TRANSITION,
                 "transition_id": _transition_id(requested), "transition_label": _transition_label(requested),
                 "start_state": None, "result_state": None, "outcome": outcome, "requested_at": asked,
                 "completed_at": None, "error": reason, "run_id": str(command.get("run_id") or "")}]
    values = command.get("values") if isinstance(command.get("values"), dict) else {}
    return [{**common, **vouching(command, str(name)), "type": PARAMETER, "name": str(name), "old": None,
             "new": finite(value), "outcome": "rejected", "reason": reason}
            for name, value in values.items()]


def parameter_fact_id(request_id: str, name: str) -> str:
    """The id of the audit fact of one parameter of a set_parameters command (once per name)."""
    return hashlib.sha256(f"{request_id}\0{name}".encode("utf-8", "surrogatepass")).hexdigest()[:32]


def unanswered_id(request_id: str) -> str:
    """The id of the site's record of a command its gateway took and did not answer."""
    return hashlib.sha256(f"unanswered\0{request_id}".encode()).hexdigest()[:32]


def vouching(command: dict, parameter: str | None = None) -> dict:
    """What the audit fact of a command carries of the site's word on who asked: its request id,
    the site's grant (for a transition; per parameter name for parameters) and the id the fact
    must have (so that a grant makes at most one record), for lifecycle_site/gateway_link/attribution.py.
    Empty for a command without grants (not the site's)."""
    request_id = str(command.get("request_id") or "")
    if parameter is None:
        grant = command.get("grant")
        return {"request_id": request_id, "grant": grant, "id": request_id} if isinstance(grant, str) else {}
    grants = command.get("grants") if isinstance(command.get("grants"), dict) else {}
    grant = grants.get(parameter)
    fields = {"id": parameter_fact_id(request_id, parameter)}
    return {**fields, "request_id": request_id, "grant": grant} if isinstance(grant, str) else fields


def _transition_id(requested: Any) -> int | None:
    from ros_gateway.shared import state_machine as sm

    text = str(requested).strip()
    if text.isdigit() and int(text) in sm.TRANSITIONS_BY_ID:
        return int(text)
    return None


def _transition_label(requested: Any) -> str:
    return transition_word(requested)


def transition_word(requested: Any) -> str:
    """A requested transition as its label ("3" and "Activate " are "activate"; an unknown word
    stays as it was asked): what an audit record calls it, and what a grant is given for."""
    from ros_gateway.shared import state_machine as sm

    transition_id = _transition_id(requested)
    if transition_id is not None:
        return sm.TRANSITIONS_BY_ID[transition_id].label
    text = str(requested)
    return text.strip().lower() if text.strip().lower() in sm.EXTERNAL_LABELS else text
