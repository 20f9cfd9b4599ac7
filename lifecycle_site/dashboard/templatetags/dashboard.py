"""Small template helpers shared by full pages and live fragments."""
from __future__ import annotations

import json

from django import template
from django.utils.translation import gettext as _
from django.utils.translation import ngettext, pgettext

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.operations import words
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
def status_word(status: str) -> str:
    """A badge's word for a node_status() (or a collapsed robot's count status): a ROS state as it
    is, the others in the active language. node_status() itself stays the code's word (classes,
    data-status, fleet.js)."""
    names = {"waiting": pgettext("node status", "waiting"), "lost": pgettext("node status", "lost"),
             "unreachable": pgettext("node status", "unreachable"), "busy": pgettext("node status", "busy")}
    return names.get(status, status)


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
    return words.title(known) if known else operation


@register.filter
def run_status_word(status: str) -> str:
    """A group run's status as its panel shows it: the stored word, in the active language."""
    known = {"queued": pgettext("run status", "queued"), "running": pgettext("run status", "running"),
             "succeeded": pgettext("run status", "succeeded"), "failed": pgettext("run status", "failed"),
             "partial": pgettext("run status", "partial")}
    return known.get(status, status)


@register.simple_tag
def robot_operations(robot: str) -> list[dict]:
    """The fleet page's buttons for a robot, from the shared table (confirmation with its name)."""
    return [{"name": op.name, "button": words.button(op), "help": words.help_line(op), "danger": op.danger,
             "confirm": words.question(op, robot), "confirm_detail": words.question_detail(op)}
            for op in operations.OPERATIONS if op.scope == operations.ROBOT]


@register.filter
def run_rank(run: dict) -> int:
    from lifecycle_site.dashboard.runs import run_rank as rank

    return rank(run)


@register.filter
def run_done(status: str) -> bool:
    from lifecycle_site.dashboard.runs import DONE_STATUSES

    return status in DONE_STATUSES


@register.filter
def run_by(run: dict) -> str:
    """Who started a run: 'by ivan', 'by ivan through the API', 'automatic recovery'."""
    source = run.get("source") or ""
    if source == "recovery" or run.get("operation") == "recover":
        return _("automatic recovery")
    user = run.get("requested_by")
    if source == "api":
        return _("by %(user)s through the API") % {"user": user} if user else _("started through the API")
    if source == "cli":
        return _("by %(user)s from the command line") % {"user": user} if user else _("started from the command line")
    return _("by %(user)s") % {"user": user} if user else _("started")


# The gateway drives a run's nodes in steps (operations/runs.py tiers(), ros_gateway/groups.py): one per
# position of the robot's bring-up order, the nodes without one last, side by side (up to 8 at a
# time). With the "stop" policy a failure starts no further node; those already under way finish.
@register.filter
def run_policy_words(run: dict) -> str:
    """What a run's failure policy does, as its steps make it work ('' for one node)."""
    known = operations.get(run.get("operation"))
    if (known is not None and known.scope != operations.ROBOT) or len(run.get("nodes") or []) == 1:
        return ""
    stop = run.get("policy") != "continue"
    steps = run.get("steps")
    if steps is not None and steps > 1:
        return _("in the bring-up order; stops at the first failure") if stop else \
            _("in the bring-up order; continues past failures")
    if steps is not None:
        return _("no bring-up order among its nodes: they run side by side, up to 8 at a time; after a failure it "
                 "starts no further node") if stop else \
            _("no bring-up order among its nodes: they run side by side, up to 8 at a time; continues past failures")
    return _("after a failure it starts no further node") if stop else _("continues past failures")


@register.filter
def age(iso: str | None) -> str:
    """'12 s ago', '3 min ago', '2 h ago' (fleet.js keeps it current in the page)."""
    if not iso:
        return ""
    from datetime import datetime, timezone

    seconds = max(0, int((datetime.now(timezone.utc) - datetime.fromisoformat(iso)).total_seconds()))
    if seconds < 60:
        return _("%(n)s s ago") % {"n": seconds}
    if seconds < 3600:
        return _("%(n)s min ago") % {"n": seconds // 60}
    return _("%(n)s h ago") % {"n": seconds // 3600}


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
    if seconds < 172800:
        return f"{seconds // 3600} h {seconds % 3600 // 60} min"
    days = seconds // 86400
    return ngettext("%(n)s day", "%(n)s days", days) % {"n": days}


OUTCOME_LABELS = dict(TransitionRecord.Outcome.choices)


@register.filter
def outcome_label(outcome: str) -> str:
    """An audit outcome as people read it ("timed out", "process lost"), as the filters name it."""
    return OUTCOME_LABELS.get(outcome, str(outcome).replace("_", " "))
