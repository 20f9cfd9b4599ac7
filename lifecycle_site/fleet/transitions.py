"""Requesting one lifecycle transition on behalf of a user, for the API and the pages alike.

The gateway checks the transition against the node's real state, calls it and records the
outcome; what is refused before reaching the gateway is recorded here, so every attempt
lands in the audit log.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from django.utils import timezone

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.gateway_client import GatewayError, GatewayOffline, call_gateway
from lifecycle_site.fleet.models import ManagedNode
from ros_gateway import protocol
from ros_gateway import state_machine as sm


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


def request_transition(node: ManagedNode, requested, user, source: str, timeout: float | None = None) -> Outcome:
    if not node.alive:
        message = f"{node.name} is not running on {node.robot.name}; it was last seen {ago(node.last_seen)}."
        record_rejection(node, requested, user, source, message)
        return Outcome(409, "node_offline", message, {"state": node.state})
    try:
        reply = call_gateway(
            protocol.CHANGE_STATE,
            timeout=timeout,
            robot=node.robot.name,
            node=node.name,
            transition=requested,
            user_id=user.pk,
            source=source,
        )
    except GatewayError as exc:
        if isinstance(exc, GatewayOffline) or exc.code == "node_offline":
            record_rejection(node, requested, user, source, exc.message)
        status = 409 if exc.code == "node_offline" else exc.status
        return Outcome(status, exc.code, exc.message, {"state": node.state, **exc.details})
    common = {"from": reply["from"], "transition": reply["transition"], "record_id": reply["record_id"]}
    outcome = reply["outcome"]
    if outcome == "succeeded":
        label = reply["transition"]["label"]
        message = f"{label} succeeded: {node.name} is now {reply['to']['label']}."
        return Outcome(200, None, message, {"success": True, **common, "to": reply["to"],
                                            "duration_ms": reply["duration_ms"]})
    if outcome == "rejected":
        return Outcome(409, "invalid_transition", reply["message"], {
            "state": reply["from"], "valid_transitions": reply["valid_transitions"], "record_id": reply["record_id"]})
    details = {"state": reply["to"], "duration_ms": reply["duration_ms"], **common}
    if outcome == "timed_out":
        return Outcome(504, "timeout", reply["message"], details)
    return Outcome(422, "transition_failed", reply["message"], details)


def record_rejection(node: ManagedNode, requested, user, source: str, message: str) -> None:
    transition = None
    try:
        transition = sm.resolve_transition(requested, node.state_id)
    except sm.UnknownTransition:
        pass
    now = timezone.now()
    TransitionRecord.objects.create(
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
