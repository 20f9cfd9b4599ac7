"""Requesting one lifecycle transition on behalf of a user, for the API and the pages alike.

The robot's gateway checks the transition against the node's real state, calls it and
reports the outcome as facts with its reply; they are applied here (ingest.facts) before the
user gets the answer. What is refused before reaching the gateway is recorded here too, so
every attempt lands in the audit log.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from django.utils import timezone
from django.utils.translation import gettext as _

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import ManagedNode
from lifecycle_site.gateway_link import gateway_input as checks
from lifecycle_site.gateway_link.gateway_client import GatewayError, call_gateway
from lifecycle_site.ingest.fact_context import Hints
from lifecycle_site.ingest.facts import apply_facts
from lifecycle_site.ingest.live_updates import push, record_messages
from lifecycle_site.refusal import Refusal, in_english, shown
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm


@dataclass
class Transitioned:
    """A transition carried out: ``message`` for people, ``data`` the API's answer."""

    message: str
    data: dict = field(default_factory=dict)


class TransitionRefused(Refusal):
    """A transition not carried out, or not as asked: refused before the node (its reason
    recorded), refused by the gateway or the node, failed, timed out, or its outcome unknown.
    ``details`` holds the node's state as known and the audit record's id when there is one."""


# HTTP status of each gateway refusal; anything else keeps GatewayError's own status.
STATUS_BY_CODE = {
    "node_offline": 409,
    "node_busy": 409,
    "robot_not_watched": 409,
    "unknown_transition": 400,
    "node_unreachable": 504,
}
# Refusals the gateway does not record itself (it never got to the node).
RECORDED_HERE = {"gateway_offline", "node_offline", "node_busy", "robot_not_watched"}


def named(requested: object) -> str | int:
    """The transition asked for, as a label or an id, if it names one at all (whether the node's
    state allows it is the gateway's to check, against the node's real state)."""
    if isinstance(requested, bool) or not isinstance(requested, (str, int)):
        raise TransitionRefused("invalid_field",
                                _("'transition' must be a label such as \"activate\" or a numeric id."))
    try:
        sm.resolve_transition(requested, sm.UNCONFIGURED)
    except sm.UnknownTransition:
        raise TransitionRefused(
            "unknown_transition", _("%(requested)s is not a lifecycle transition; use one of %(labels)s or an id "
                                    "1-7.") % {"requested": shown(requested), "labels": ", ".join(sm.EXTERNAL_LABELS)}
        ) from None
    if isinstance(requested, str):  # (a name it resolved: digits are few)
        text = requested.strip()
        return int(text) if text.isascii() and text.isdigit() else text.lower()
    return requested


def request_transition(node: ManagedNode, requested: object, user, source: str,
                       timeout: float | None = None) -> Transitioned:
    """Carry out one transition for ``user``; raises TransitionRefused for anything else than
    success (the audit record exists before either)."""
    requested = named(requested)
    if not node.robot.enabled or not node.alive:
        # Shown in the asker's language, recorded in English.
        record = record_rejection(node, requested, user, source, in_english(not_watched, node))
        raise TransitionRefused("node_offline", not_watched(node), 409, state=node.state, record_id=record.id)
    gateway = node.robot.gateway.name
    try:
        reply = call_gateway(
            gateway,
            protocol.CHANGE_STATE,
            timeout=timeout,
            robot=node.robot.name,
            node=node.name,
            transition=requested,
            user_id=user.pk,
            source=source,
        )
    except GatewayError as exc:
        details = {"state": node.state, **exc.details}
        record = _apply(gateway, exc.facts, Hints(node, user))
        if record is not None:
            details["record_id"] = record.id
        elif exc.code in RECORDED_HERE:
            details["record_id"] = record_rejection(node, requested, user, source, exc.english).id
        raise TransitionRefused(exc.code, exc.message, STATUS_BY_CODE.get(exc.code, exc.status), **details) from None
    record = _apply(gateway, reply.get("facts") or [], Hints(node, user))
    record_id = record.id if record is not None else None
    try:
        reply = checks.change_state_reply(reply)
    except checks.GatewayInputRefused as exc:
        message = _("Gateway %(gateway)s answered with a reply the site cannot read (%(reason)s): whether "
                    "%(transition)s reached %(node)s is not known. Check the node's state before you try again.") % {
            "gateway": gateway, "reason": exc, "transition": requested, "node": node.name}
        raise TransitionRefused("gateway_error", message, 502, state=node.state, record_id=record_id) from None
    common = {"from": reply["from"], "transition": reply["transition"], "record_id": record_id}
    outcome = reply["outcome"]
    if outcome == "succeeded":
        label = (reply["transition"] or {}).get("label", str(requested))
        values = {"transition": label, "node": node.name, "state": (reply["to"] or {}).get("label")}
        if values["state"] is None:
            message = _("%(transition)s succeeded: %(node)s is now in an unknown state.") % values
        else:
            message = _("%(transition)s succeeded: %(node)s is now %(state)s.") % values
        return Transitioned(message, {"success": True, **common, "to": reply["to"],
                                      "duration_ms": reply["duration_ms"]})
    if outcome == "rejected":
        raise TransitionRefused("invalid_transition", reply["message"], 409, state=reply["from"],
                                valid_transitions=reply["valid_transitions"], record_id=record_id)
    details = {"state": reply["to"], "duration_ms": reply["duration_ms"], **common}
    if outcome == "timed_out":
        raise TransitionRefused("timeout", reply["message"], 504, **details)
    if outcome == protocol.PROCESS_LOST:  # the node's process ended during the transition
        raise TransitionRefused("process_lost", reply["message"], 422, **details)
    raise TransitionRefused("transition_failed", reply["message"], 422, **details)


def not_watched(node: ManagedNode) -> str:
    """Why no transition is sent to the node: its robot is disabled, or it is not running."""
    if not node.robot.enabled:
        return _("Robot %(robot)s is disabled: its nodes are not watched. Enable it in the admin.") % {
            "robot": node.robot.name}
    if node.last_seen is None:
        return _("%(node)s is not running on %(robot)s, and has never been seen running.") % {
            "node": node.name, "robot": node.robot.name}
    return _("%(node)s is not running on %(robot)s; it was last seen %(ago)s.") % {
        "node": node.name, "robot": node.robot.name, "ago": ago(node.last_seen)}


def _apply(gateway: str, facts: list, hints: Hints) -> TransitionRecord | None:
    """Store what the gateway reported with its reply (the node's new state, the audit record
    of the attempt) and show the record on the node's page; returns that record."""
    if not facts:
        return None
    applied = apply_facts(gateway, facts, hints)
    push(record_messages(applied.created))
    return applied.transition_record(facts)


def record_rejection(node: ManagedNode, requested, user, source: str, message: str) -> TransitionRecord:
    transition = None
    try:
        transition = sm.resolve_transition(requested, node.state_id)
    except sm.UnknownTransition:
        pass
    now = timezone.now()
    return TransitionRecord.objects.create(
        node=node,
        robot=node.robot,
        robot_name=node.robot.name,
        node_name=node.name,
        transition_id=transition.id if transition else None,
        transition_label=transition.label if transition else str(requested),
        start_state_id=node.state_id,
        start_state_label=node.state_label,
        outcome=TransitionRecord.Outcome.REJECTED,
        source=source,
        requested_by=user,
        requested_at=now,
        completed_at=now,
        duration_ms=0.0,
        error=message,
    )


def ago(moment) -> str:
    if moment is None:
        return _("never")
    seconds = int((timezone.now() - moment).total_seconds())
    if seconds < 120:
        return _("%(n)s s ago") % {"n": seconds}
    if seconds < 7200:
        return _("%(n)s min ago") % {"n": seconds // 60}
    return moment.strftime("%Y-%m-%d %H:%M UTC")
