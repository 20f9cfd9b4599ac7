"""What a gateway sends, checked before the database or any page sees it.

A gateway is a stranger (it runs on a plant-floor device): its facts, replies and live updates
are input. Each value is taken only in the shape the site expects, rebuilt from checked parts
(never passed on as sent), and bounded in size. Robot names are matched exactly against the
gateway's own robots: no case folding, no trimming, no look-alikes. What fails is refused with
a reason (GatewayInputRefused, a FactRejected for the fact path) and counted by the caller.
"""
from __future__ import annotations

import json
import re
from datetime import datetime, timedelta, timezone
from typing import Any, Iterable

from ros_gateway.shared import operations, protocol
from ros_gateway.shared import state_machine as sm

# A fully qualified ROS node name: /name or /namespace/name (rcl's rules: letters, digits and
# underscores, no part starting with a digit).
NODE_NAME_RE = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")
NODE_NAME_LENGTH = 255
TEXT_LENGTH = 4000  # an error, a reason, a run's message: what a person reads
LABEL_LENGTH = 64
VALUE_BYTES = 16 * 1024  # a parameter value, as JSON
RUN_ID_RE = re.compile(r"^[0-9a-f]{1,32}$")
RUN_RESULTS = 2000  # nodes in one run's results
RUN_STEPS = 8  # transitions of one node in a run (a restart takes four)
RUN_NODES = 100  # node pages told of one run update (those finished since the last one)
CHANGES = 500  # parameters in one live update
# A time a gateway reports may be a little ahead of the site's clock, not years.
CLOCK_SKEW = timedelta(hours=1)
EARLIEST = datetime(2000, 1, 1, tzinfo=timezone.utc)
GONE_REASONS = ("", "unreachable", protocol.PROCESS_LOST)
PROCESS_STATUSES = ("", "lost", "restarted")
RESULT_OUTCOMES = ("succeeded", "failed", "skipped", "not_run", "timed_out", "rejected", protocol.PROCESS_LOST)


class FactRejected(ValueError):
    """A fact the site cannot apply (malformed, or about what its gateway does not own)."""


def parse_time(value: Any, what: str = "time") -> datetime:
    """An ISO-8601 time as an aware datetime (UTC when it carries no offset)."""
    try:
        moment = datetime.fromisoformat(str(value))
    except ValueError:
        raise FactRejected(f"{what} {value!r} is not an ISO-8601 time") from None
    return moment if moment.tzinfo else moment.replace(tzinfo=timezone.utc)


class GatewayInputRefused(FactRejected):
    """Something a gateway sent that the site does not take (the message says why)."""


def text(value: Any, limit: int = TEXT_LENGTH) -> str:
    """A string, cut to ``limit`` characters and storable by every database (None is "");
    anything else is refused."""
    if value is None:
        return ""
    if not isinstance(value, str):
        raise GatewayInputRefused(f"expected text, got {type(value).__name__}")
    return _storable_text(value[:limit])


def node_name(value: Any) -> str:
    if not isinstance(value, str) or len(value) > NODE_NAME_LENGTH or not NODE_NAME_RE.match(value):
        raise GatewayInputRefused(f"{str(value)[:80]!r} is not a fully qualified ROS node name")
    return value


def owned_robot(value: Any, robots: dict[str, Any], gateway: str) -> Any:
    """The robot named ``value`` exactly, if it is one of ``robots`` (the gateway's own)."""
    if not isinstance(value, str) or value not in robots:
        raise GatewayInputRefused(f"robot {str(value)[:80]!r} is not one of gateway {gateway}'s robots")
    return robots[value]


def state_id(value: Any) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or value not in sm.STATE_LABELS:
        raise GatewayInputRefused(f"{str(value)[:20]!r} is not a lifecycle state id")
    return value


def optional_state_id(value: Any) -> int | None:
    return None if value is None else state_id(value)


def choice(value: Any, allowed: Iterable[str], what: str) -> str:
    value = "" if value is None else value
    if value not in tuple(allowed):
        raise GatewayInputRefused(f"{what} {str(value)[:40]!r} is not one the site knows")
    return value


def moment(value: Any, what: str = "time") -> datetime:
    """An ISO-8601 time, plausible: not before 2000, not beyond CLOCK_SKEW ahead of now."""
    if not isinstance(value, str) or len(value) > 40:
        raise GatewayInputRefused(f"{what} must be an ISO-8601 time")
    try:
        found = datetime.fromisoformat(value)
    except ValueError:
        raise GatewayInputRefused(f"{what} {value!r} is not an ISO-8601 time") from None
    found = found if found.tzinfo else found.replace(tzinfo=timezone.utc)
    if not EARLIEST <= found <= datetime.now(timezone.utc) + CLOCK_SKEW:
        raise GatewayInputRefused(f"{what} {value} is not a plausible time (clock off?)")
    return found


def optional_moment(value: Any, what: str) -> datetime | None:
    return None if value in (None, "") else moment(value, what)


def value(found: Any) -> Any:
    """A parameter value: JSON of at most VALUE_BYTES, else a note of what it was (so the record
    still says a value was set, not what it was)."""
    try:
        encoded = protocol.encode({"v": found})
    except (TypeError, ValueError):
        return f"(a value the site cannot store: {type(found).__name__})"
    if len(encoded) > VALUE_BYTES + 6:
        return f"(a value of {len(encoded) - 6} bytes as JSON, not kept: at most {VALUE_BYTES})"
    return json.loads(encoded)["v"]


def _storable_text(found: str) -> str:
    """A string inside a JSON value as every database stores it: PostgreSQL's jsonb refuses NUL
    characters and lone UTF-16 surrogates (SQLite keeps both, escaped); they become U+FFFD."""
    return found.replace("\x00", "\ufffd").encode("utf-8", "surrogatepass").decode("utf-8", "replace")


def storable(found: Any) -> Any:
    """A parameter value with its strings storable (see _storable_text)."""
    if isinstance(found, str):
        return _storable_text(found)
    if isinstance(found, list):
        return [storable(item) for item in found]
    if isinstance(found, dict):
        return {_storable_text(str(key)): storable(item) for key, item in found.items()}
    return found


def user_id(found: Any) -> int | None:
    if found is None:
        return None
    if not isinstance(found, int) or isinstance(found, bool) or found < 1:
        raise GatewayInputRefused("user_id must be a positive whole number")
    return found


# --- live updates ---------------------------------------------------------------------------

def node_payload(node: Any, robots: dict[str, Any], gateway: str) -> tuple[dict, Any]:
    """A ``node.state`` update's node, rebuilt from its checked fields; and its robot."""
    if not isinstance(node, dict):
        raise GatewayInputRefused("node.state needs a node object")
    robot = owned_robot(node.get("robot"), robots, gateway)
    name = node_name(node.get("name"))
    state = node.get("state")
    process = node.get("process") if isinstance(node.get("process"), dict) else {}
    alive = node.get("alive")
    if not isinstance(alive, bool):
        raise GatewayInputRefused("alive must be true or false")
    last_seen = optional_moment(node.get("last_seen"), "last_seen")
    since = optional_moment(process.get("since"), "process since")
    payload = protocol.node_payload(
        key=protocol.node_key(robot.name, name), robot=robot.name, name=name,
        state_id=state_id(state.get("id") if isinstance(state, dict) else None), alive=alive,
        last_seen=last_seen.isoformat() if last_seen else None,
        gone_reason=choice(node.get("gone_reason"), GONE_REASONS, "gone_reason"),
        process_status=choice(process.get("status"), PROCESS_STATUSES, "process status"),
        process_since=since.isoformat() if since else None,
    )
    return payload, robot


def parameter_update(message: dict, robots: dict[str, Any], gateway: str) -> tuple[str, list[dict]]:
    """A ``node.parameters`` update: its node's key and the checked changes."""
    if "robot" in message or "name" in message:
        robot = owned_robot(message.get("robot"), robots, gateway)
        name = node_name(message.get("name"))
    else:  # a gateway of before 2026-11 names the node by its key only
        key = message.get("node")
        robot_name, _, rest = key.partition(".") if isinstance(key, str) else ("", "", "")
        robot = owned_robot(robot_name, robots, gateway)
        name = node_name("/" + rest.replace(".", "/"))
    changes = message.get("changes")
    if not isinstance(changes, list) or len(changes) > CHANGES:
        raise GatewayInputRefused(f"changes must be a list of at most {CHANGES}")
    checked = []
    for change in changes:
        if not isinstance(change, dict):
            raise GatewayInputRefused("each change must be an object")
        checked.append({"name": text(change.get("name"), NODE_NAME_LENGTH), "old": value(change.get("old")),
                        "new": value(change.get("new"))})
    return protocol.node_key(robot.name, name), checked


def run_progress(message: dict, robots: dict[str, Any], gateway: str) -> tuple[dict, Any, list[str]]:
    """A ``run.progress`` update: the run (rebuilt), its robot, and the node keys it names."""
    run = message.get("run")
    if not isinstance(run, dict):
        raise GatewayInputRefused("run.progress needs a run object")
    robot = owned_robot(run.get("robot"), robots, gateway)
    run_id = run.get("id")
    if not isinstance(run_id, str) or not RUN_ID_RE.match(run_id):
        raise GatewayInputRefused("a run id is up to 32 hexadecimal digits")
    from lifecycle_site.fleet.models import GroupRun

    checked = {
        "id": run_id, "robot": robot.name,
        "operation": choice(run.get("operation"), list(operations.BY_NAME), "operation"),
        "policy": choice(run.get("policy"), GroupRun.Policy.values, "policy"),
        "status": choice(run.get("status"), GroupRun.Status.values, "run status"),
        "message": text(run.get("message")),
        "results": run_results(run.get("results")),
    }
    nodes = message.get("nodes") or []
    if not isinstance(nodes, list):
        raise GatewayInputRefused("nodes must be a list of node keys")
    # Only nodes of the run's results (a node page shows the runs of its node), and a bounded few.
    keys = {protocol.node_key(robot.name, result["node"]) for result in checked["results"]}
    return checked, robot, [key for key in nodes[:RUN_NODES] if key in keys]


def run_results(results: Any) -> list[dict]:
    """A run's per-node results (shown on pages and kept with the run), rebuilt and bounded."""
    if results is None:
        return []
    if not isinstance(results, list) or len(results) > RUN_RESULTS:
        raise GatewayInputRefused(f"results must be a list of at most {RUN_RESULTS}")
    checked = []
    for result in results:
        if not isinstance(result, dict):
            raise GatewayInputRefused("each result must be an object")
        entry: dict[str, Any] = {"node": node_name(result.get("node")),
                                 "outcome": choice(result.get("outcome"), RESULT_OUTCOMES, "outcome")}
        if result.get("node_id") is not None:
            entry["node_id"] = text(result.get("node_id"), 300)
        if result.get("message"):
            entry["message"] = text(result.get("message"))
        if isinstance(result.get("duration_ms"), (int, float)) and not isinstance(result.get("duration_ms"), bool):
            entry["duration_ms"] = float(result["duration_ms"])
        if isinstance(result.get("state"), dict):
            found = state_id(result["state"].get("id"))
            entry["state"] = sm.state_dict(found)
        steps = result.get("steps") or []
        if not isinstance(steps, list) or len(steps) > RUN_STEPS:
            raise GatewayInputRefused(f"steps must be a list of at most {RUN_STEPS}")
        entry["steps"] = [_step(step) for step in steps]
        checked.append(entry)
    return checked


def _step(step: Any) -> dict:
    if not isinstance(step, dict):
        raise GatewayInputRefused("each step must be an object")
    checked: dict[str, Any] = {"transition": text(step.get("transition"), LABEL_LENGTH),
                               "outcome": choice(step.get("outcome"), RESULT_OUTCOMES, "step outcome")}
    if step.get("message"):
        checked["message"] = text(step.get("message"))
    if isinstance(step.get("duration_ms"), (int, float)) and not isinstance(step.get("duration_ms"), bool):
        checked["duration_ms"] = float(step["duration_ms"])
    if isinstance(step.get("fact_id"), str):
        checked["fact_id"] = step["fact_id"][:32]
    if isinstance(step.get("to"), dict):
        checked["to"] = sm.state_dict(state_id(step["to"].get("id")))
    return checked


# --- replies to the site's commands -----------------------------------------------------------

ERROR_CODE_RE = re.compile(r"^[a-z_]{1,40}$")


def failure(reply: dict) -> tuple[str, str]:
    """A failed reply's (code, message)."""
    error = reply.get("error") if isinstance(reply.get("error"), dict) else {}
    code = error.get("code")
    return (code if isinstance(code, str) and ERROR_CODE_RE.match(code) else "gateway_error",
            text(error.get("message")) if isinstance(error.get("message"), str) else "")


def _state(found: Any) -> dict | None:
    return None if found is None else sm.state_dict(state_id(found.get("id") if isinstance(found, dict) else None))


def change_state_reply(reply: dict) -> dict:
    """A change_state reply's fields, rebuilt: states and transitions from the state machine."""
    transition = reply.get("transition")
    if transition is not None:
        if not isinstance(transition, dict) or not _transition_id(transition.get("id")):
            raise GatewayInputRefused("its transition is not one of the lifecycle state machine")
        transition = sm.TRANSITIONS_BY_ID[transition["id"]].as_dict()
    valid = reply.get("valid_transitions") or []
    if not isinstance(valid, list) or len(valid) > 32:
        raise GatewayInputRefused("valid_transitions must be a short list")
    duration = reply.get("duration_ms")
    return {
        "outcome": choice(reply.get("outcome"), RESULT_OUTCOMES, "outcome"),
        "transition": transition,
        "from": _state(reply.get("from")),
        "to": _state(reply.get("to")),
        "duration_ms": float(duration) if isinstance(duration, (int, float)) and not isinstance(duration, bool)
        and duration == duration and abs(duration) < 1e9 else None,
        "message": text(reply.get("message")),
        "valid_transitions": [sm.TRANSITIONS_BY_ID[t["id"]].as_dict() for t in valid
                              if isinstance(t, dict) and _transition_id(t.get("id"))],
    }


def _transition_id(found: Any) -> bool:
    return isinstance(found, int) and not isinstance(found, bool) and found in sm.TRANSITIONS_BY_ID


def parameter_results(results: Any, asked: Iterable[str]) -> list[dict]:
    """A set_parameters reply's results: one per parameter the site asked for, no others."""
    asked = list(asked)
    if not isinstance(results, list) or len(results) > len(asked):
        raise GatewayInputRefused("its results must be one per parameter asked for")
    checked = []
    for result in results:
        if not isinstance(result, dict) or result.get("name") not in asked:
            raise GatewayInputRefused("a result names a parameter the site did not ask for")
        if not isinstance(result.get("successful"), bool):
            raise GatewayInputRefused("each result must say whether it was successful")
        entry = {"name": result["name"], "old": value(result.get("old")), "new": value(result.get("new")),
                 "successful": result["successful"], "reason": text(result.get("reason"))}
        checked.append(entry)
    return checked


def small_list(found: Any, what: str, limit: int = 64 * 1024) -> list:
    """A list a reply carries for a page or the API to show as it is (states, a transition
    graph): it must be a list, and small."""
    if not isinstance(found, list) or len(protocol.encode({"v": found})) > limit:
        raise GatewayInputRefused(f"{what} must be a list of at most {limit:,} bytes")
    return found
