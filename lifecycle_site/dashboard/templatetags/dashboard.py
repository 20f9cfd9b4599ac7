"""Small template helpers shared by full pages and live fragments."""
from __future__ import annotations

import json

from django import template

from lifecycle_site.audit.models import TransitionRecord
from ros_gateway.shared import operations

register = template.Library()


@register.filter
def dom_id(node_key: str) -> str:
    """A CSS-selector-safe element id for a node (htmx looks ids up as '#id' selectors).

    Node keys contain dots; ROS names never contain '__', so it is a safe stand-in.
    """
    return "node-" + node_key.replace(".", "__")


@register.filter
def node_status(node: dict) -> str:
    """What the badge says: the state, or why there is none (lost, unreachable, waiting)."""
    if node["alive"]:
        return node["state"]["label"]
    if node.get("last_seen") is None:
        return "waiting"
    return "unreachable" if node.get("gone_reason") == "unreachable" else "lost"


@register.filter
def short_time(iso: str | None) -> str:
    """'14:03:27' for today, '2026-11-20 14:03' otherwise (UTC, as stored)."""
    if not iso:
        return ""
    from datetime import datetime, timezone

    moment = datetime.fromisoformat(iso).astimezone(timezone.utc)
    if moment.date() == datetime.now(timezone.utc).date():
        return moment.strftime("%H:%M:%S")
    return moment.strftime("%Y-%m-%d %H:%M")


@register.filter
def stamp(iso: str | None) -> str:
    """'2026-11-22 04:10:35' from an ISO timestamp (UTC)."""
    if not iso:
        return ""
    from datetime import datetime, timezone

    return datetime.fromisoformat(iso).astimezone(timezone.utc).strftime("%Y-%m-%d %H:%M:%S")


@register.filter
def make_list_words(text: str) -> list[str]:
    return text.split()


@register.filter
def param_dom(name: str) -> str:
    """A selector-safe id part: parameter names may hold dots and slashes (QoS overrides)."""
    import re

    return re.sub(r"[^A-Za-z0-9_]", "-", name)


@register.filter
def json_value(value) -> str:
    if isinstance(value, str):
        return value
    return json.dumps(value)


@register.simple_tag
def json_object(*pairs) -> str:
    """A JSON object from key, value pairs, for an attribute (hx-vals, hx-headers):
    ``hx-vals="{% json_object 'transition' t.label %}"``.

    Values are escaped for JSON here and, as a simple tag's output, for HTML by autoescaping
    (quotes included): a name a robot reports stays one value, whatever it holds. Pasting
    ``"{{ t.label }}"`` into JSON text let a label add keys of its own."""
    if len(pairs) % 2:
        raise template.TemplateSyntaxError("json_object takes key, value pairs")
    # default=str: lazy strings such as the csrf_token of the context.
    return json.dumps(dict(zip(pairs[::2], pairs[1::2], strict=True)), default=str)


@register.filter
def get_item(mapping, key):
    return (mapping or {}).get(key)


@register.filter
def all_successful(results: dict) -> bool:
    return all(r.get("successful") for r in results.values())


@register.filter
def operation_label(operation: str) -> str:
    known = operations.get(operation)
    return known.title if known else operation


@register.simple_tag
def robot_operations(robot: str) -> list[dict]:
    """The fleet page's buttons for a robot, from the shared table (confirmation with its name)."""
    return [{"name": op.name, "button": op.button, "help": op.help, "danger": op.danger,
             "confirm": op.confirm_text(robot), "confirm_detail": op.confirm_detail}
            for op in operations.OPERATIONS if op.scope == operations.ROBOT]


@register.filter
def run_rank(run: dict) -> int:
    from lifecycle_site.dashboard.runs import run_rank as rank

    return rank(run)


@register.filter
def run_done(status: str) -> bool:
    from lifecycle_site.dashboard.runs import DONE_STATUSES

    return status in DONE_STATUSES


RUN_SOURCES = {"api": "through the API", "cli": "from the command line", "dashboard": "", "external": ""}


@register.filter
def run_by(run: dict) -> str:
    """Who started a run: 'by ivan', 'by ivan through the API', 'automatic recovery'."""
    source = run.get("source") or ""
    if source == "recovery" or run.get("operation") == "recover":
        return "automatic recovery"
    how = RUN_SOURCES.get(source, "")
    if run.get("requested_by"):
        return f"by {run['requested_by']}" + (f" {how}" if how else "")
    return f"started {how}" if how else "started"


# The gateway drives a run's nodes in steps (operations/runs.py tiers(), ros_gateway/groups.py): one per
# position of the robot's bring-up order, the nodes without one last, side by side (up to 8 at a
# time). With the "stop" policy a failure starts no further node; those already under way finish.
SIDE_BY_SIDE = "no bring-up order among its nodes: they run side by side, up to 8 at a time"


@register.filter
def run_policy_words(run: dict) -> str:
    """What a run's failure policy does, as its steps make it work ('' for one node)."""
    known = operations.get(run.get("operation"))
    if (known is not None and known.scope != operations.ROBOT) or len(run.get("nodes") or []) == 1:
        return ""
    stop = run.get("policy") != "continue"
    steps = run.get("steps")
    if steps is not None and steps > 1:
        return "in the bring-up order; " + ("stops at the first failure" if stop else "continues past failures")
    if steps is not None:
        return SIDE_BY_SIDE + ("; after a failure it starts no further node" if stop else "; continues past failures")
    return "after a failure it starts no further node" if stop else "continues past failures"


@register.filter
def age(iso: str | None) -> str:
    """'12 s ago', '3 min ago', '2 h ago' (fleet.js keeps it current in the page)."""
    if not iso:
        return ""
    from datetime import datetime, timezone

    seconds = max(0, int((datetime.now(timezone.utc) - datetime.fromisoformat(iso)).total_seconds()))
    if seconds < 60:
        return f"{seconds} s ago"
    if seconds < 3600:
        return f"{seconds // 60} min ago"
    return f"{seconds // 3600} h ago"


@register.filter
def elapsed(iso: str | None) -> str:
    """'12 s', '3 min', '5 h 12 min', '3 days': how long since ``iso`` (live.js keeps it current in
    the page, the same way)."""
    if not iso:
        return "0 s"
    from datetime import datetime, timezone

    seconds = max(0, int((datetime.now(timezone.utc) - datetime.fromisoformat(iso)).total_seconds()))
    if seconds < 120:
        return f"{seconds} s"
    if seconds < 7200:
        return f"{seconds // 60} min"
    return f"{seconds // 3600} h {seconds % 3600 // 60} min" if seconds < 172800 else f"{seconds // 86400} days"


OUTCOME_LABELS = dict(TransitionRecord.Outcome.choices)


@register.filter
def outcome_label(outcome: str) -> str:
    """An audit outcome as people read it ("timed out", "process lost"), as the filters name it."""
    return OUTCOME_LABELS.get(outcome, str(outcome).replace("_", " "))
