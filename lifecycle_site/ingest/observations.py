"""What the ingest process saw of the nodes' states in the facts it stored, handed to whoever
watches (ingest/watchers.py: the alert rules), across ingest processes too (shares.py)."""
from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

from lifecycle_site.gateway_link.gateway_input import FactRejected, parse_time
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm

GONE = "gone"  # an observation's state when a node.gone fact reported it


@dataclass(frozen=True)
class Observation:
    """A node's state as one fact reported it, at the gateway's time."""

    gateway: str
    robot: str
    node: str
    state: str  # a state label, or GONE
    at: datetime
    reason: str = ""



def observations(gateway: str, facts: list[dict]) -> list[Observation]:
    """The node states and departures among a batch of facts (malformed ones are skipped:
    ingest.facts has rejected and counted them)."""
    seen = []
    for fact in facts:
        if not isinstance(fact, dict) or fact.get("type") not in (protocol.NODE_STATE, protocol.NODE_GONE):
            continue
        try:
            at = parse_time(fact.get("at"), "at")
            if fact["type"] == protocol.NODE_STATE:
                state = sm.state_label(int(fact["state_id"]))
            else:
                state = GONE
            seen.append(Observation(gateway, str(fact["robot"]), str(fact["node"]), state, at,
                                    str(fact.get("reason") or "")))
        except (KeyError, TypeError, ValueError, FactRejected):
            continue
    return seen
