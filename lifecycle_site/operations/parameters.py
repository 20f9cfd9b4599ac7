"""A node's parameters through its gateway: listed with descriptors, and set (checked by the node,
each name audited whatever fails), for the API and the node page alike."""
from __future__ import annotations

from django.utils.translation import gettext_noop

from lifecycle_site.audit.models import ParameterRecord
from lifecycle_site.gateway_link import gateway_input as checks
from lifecycle_site.gateway_link.gateway_client import GatewayError, call_gateway
from lifecycle_site.ingest.facts import apply_facts
from lifecycle_site.ingest.live_updates import AUDIT_STORED, push, record_messages
from lifecycle_site.refusal import both
from ros_gateway.shared import protocol


def fetch(node) -> list[dict]:
    gateway = node.robot.gateway.name
    listing = call_gateway(gateway, protocol.GET_PARAMETERS, robot=node.robot.name, node=node.name).get("parameters")
    if not isinstance(listing, list) or not all(isinstance(p, dict) and isinstance(p.get("name"), str)
                                                 for p in listing):
        text, english = both(gettext_noop("Gateway %(gateway)s answered with a parameter list the site cannot read."),
                             gateway=gateway)
        raise GatewayError("gateway_error", text, carried_out=False, english=english)
    return listing


def apply(node, values: dict, user, source: str, atomic: bool = False) -> list[dict]:
    """Set parameters through the node's gateway (``atomic``: all or none, in one call of the
    node's set_parameters_atomically); every requested name is audited: by the
    facts that come with the answer (the gateway's, or the site's for a command it withdrew),
    applied here before answering, or here when nothing reached the node. Only when the gateway
    took the command and did not answer is the record left to it (it reports what it did)."""
    gateway = node.robot.gateway.name
    user_id = user.pk if getattr(user, "pk", None) else None
    try:
        reply = call_gateway(gateway, protocol.SET_PARAMETERS, robot=node.robot.name, node=node.name,
                             values=values, user_id=user_id, source=source, **({"atomic": True} if atomic else {}))
    except GatewayError as exc:
        if exc.facts:
            _store(gateway, exc.facts)
        elif exc.carried_out is False:
            for name, value in values.items():
                ParameterRecord(node=node, robot_name=node.robot.name, node_name=node.name, name=name,
                                new_value=protocol.finite(value), outcome="rejected", reason=exc.english,
                                source=source, requested_by_id=user_id, at=exc.requested_at).save()
            push([AUDIT_STORED])
        raise
    if reply.get("facts"):
        _store(gateway, reply["facts"])
    try:
        return checks.parameter_results(reply.get("results"), values)
    except checks.GatewayInputRefused as exc:  # (its reason in English, as logged and counted)
        text, english = both(gettext_noop(
            "Gateway %(gateway)s answered with results the site cannot read (%(reason)s); the audit log shows what it "
            "reported. Check the parameters before you try again."), gateway=gateway, reason=exc)
        raise GatewayError("gateway_error", text, carried_out=None, english=english) from None


def _store(gateway: str, facts: list) -> None:
    """Apply a reply's facts and tell the open audit pages (the ingest process will find them
    stored already)."""
    applied = apply_facts(gateway, facts)
    push(record_messages(applied.created, applied.created_parameters))
