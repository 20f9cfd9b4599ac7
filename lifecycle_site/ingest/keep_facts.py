"""What a gateway reports about keeping robots as their modes and desired states say.

- It stopped keeping a node in its desired state (ros_gateway/desired_keeper.py: another manager
  keeps moving it): the node says so on its pages and in the alerts ("another manager keeps
  changing ..."), and the gateway's config says "paused" for it until an operator resumes it
  (operations/desired_state.py).
- The rates of the topics the robot's mode waits for (ros_gateway/topic_rates.py).

Checked like every fact: nodes and topics of the gateway's own robots, bounded numbers and text."""
from __future__ import annotations

from datetime import datetime

from lifecycle_site.gateway_link import gateway_input as checks
from lifecycle_site.gateway_link.gateway_config import publish_on_commit
from lifecycle_site.ingest.fact_context import Applied, KnownRecords
from lifecycle_site.modes.models import CurrentMode, TopicRate
from ros_gateway.shared import param_types as pt
from ros_gateway.shared import protocol

NOTE_LENGTH = 1000


def apply_enforcement_stopped(known: KnownRecords, fact: dict, at: datetime, applied: Applied) -> None:
    robot = known.robot(fact)
    node = known.node(robot, checks.node_name(fact.get("node")))
    if node is None:
        return
    note = checks.text(fact.get("message"), NOTE_LENGTH)
    type(node).objects.filter(pk=node.pk, enforcement_stopped__isnull=True).update(
        enforcement_stopped=at, enforcement_note=note)
    publish_on_commit([known.name])  # its config now says "paused" for the node


def apply_topic_rates(known: KnownRecords, fact: dict, at: datetime, applied: Applied) -> None:
    """How often a robot's topics are published, as its gateway measured them (for a mode's
    readiness): only topics its current mode asks for are kept."""
    robot = known.robot(fact)
    rates = fact.get("rates")
    if not isinstance(rates, list) or len(rates) > protocol.MAX_RATE_TOPICS:
        raise checks.GatewayInputRefused(f"rates must be a list of at most {protocol.MAX_RATE_TOPICS}")
    now_mode = CurrentMode.objects.select_related("mode").filter(robot=robot).first()
    asked = {t["topic"] for t in now_mode.topics()} if now_mode else set()
    for item in rates:
        if not isinstance(item, dict) or item.get("topic") not in asked:
            continue
        hz, window = item.get("hz"), item.get("window_s")
        if hz is not None and not (pt.is_number(hz) and 0 <= hz < 1e7):
            raise checks.GatewayInputRefused("hz must be a number of messages per second, or null")
        TopicRate.objects.update_or_create(robot=robot, topic=item["topic"], defaults={
            "hz": hz, "window_s": float(window) if pt.is_number(window) else 5.0, "at": at})
