"""Requesting one lifecycle transition on behalf of a user, for the API and the pages alike.

The robot's gateway checks the transition against the node's real state, calls it and
reports the outcome as facts with its reply; they are applied here (fleet.facts) before the
user gets the answer. What is refused before reaching the gateway is recorded here too, so
every attempt lands in the audit log.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from django.utils import timezone

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet import gateway_input as checks
from lifecycle_site.fleet.fact_context import Hints
from lifecycle_site.fleet.facts import apply_facts
from lifecycle_site.fleet.gateway_client import GatewayError, call_gateway
from lifecycle_site.fleet.live_updates import push, record_messages
from lifecycle_site.fleet.models import ManagedNode
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm


@dataclass
class Outcome:
    """What became of a request: ``code`` is None on success."""

    status: int
    code: str | None
    message: str
    data: dict = field(default_factory=dict)

    @property
    def succeeded(self) -> bool:
        return self.code is None


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


def request_transition(node: ManagedNode, requested, user, source: str, timeout: float | None = None) -> Outcome:
    if not node.robot.enabled or not node.alive:
        if not node.robot.enabled:
            message = f"Robot {node.robot.name} is disabled: its nodes are not watched. Enable it in the admin."
        else:
            message = f"{node.name} is not running on {node.robot.name}; it was last seen {ago(node.last_seen)}."
        record = record_rejection(node, requested, user, source, message)
        return Outcome(409, "node_offline", message, {"state": node.state, "record_id": record.id})
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
            details["record_id"] = record_rejection(node, requested, user, source, exc.message).id
        return Outcome(STATUS_BY_CODE.get(exc.code, exc.status), exc.code, exc.message, details)
    record = _apply(gateway, reply.get("facts") or [], Hints(node, user))
    try:
        reply = checks.change_state_reply(reply)
    except checks.GatewayInputRefused as exc:
        message = (f"Gateway {gateway} answered with a reply the site cannot read ({exc}): whether "
                   f"{requested} reached {node.name} is not known. Check the node's state before you try again.")
        return Outcome(502, "gateway_error", message, {"state": node.state,
                                                      "record_id": record.id if record is not None else None})
    common = {"from": reply["from"], "transition": reply["transition"],
              "record_id": record.id if record is not None else None}
    outcome = reply["outcome"]
    if outcome == "succeeded":
        label = (reply["transition"] or {}).get("label", str(requested))
        message = f"{label} succeeded: {node.name} is now {(reply['to'] or {}).get('label', 'in an unknown state')}."
        return Outcome(200, None, message, {"success": True, **common, "to": reply["to"],
                                            "duration_ms": reply["duration_ms"]})
    if outcome == "rejected":
        return Outcome(409, "invalid_transition", reply["message"], {
            "state": reply["from"], "valid_transitions": reply["valid_transitions"], "record_id": common["record_id"]})
    details = {"state": reply["to"], "duration_ms": reply["duration_ms"], **common}
    if outcome == "timed_out":
        return Outcome(504, "timeout", reply["message"], details)
    if outcome == protocol.PROCESS_LOST:  # the node's process ended during the transition
        return Outcome(422, "process_lost", reply["message"], details)
    return Outcome(422, "transition_failed", reply["message"], details)


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
        return "never"
    seconds = int((timezone.now() - moment).total_seconds())
    if seconds < 120:
        return f"{seconds} s ago"
    if seconds < 7200:
        return f"{seconds // 60} min ago"
    return moment.strftime("%Y-%m-%d %H:%M UTC")
