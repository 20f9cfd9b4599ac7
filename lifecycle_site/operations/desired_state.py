"""The state automatic recovery brings a node back to after its process restarts (the robot's
gateway reads it with its configuration), set from the API and the node page alike."""
from __future__ import annotations

from lifecycle_site.fleet.models import ManagedNode
from lifecycle_site.refusal import Refusal


def set_desired_state(node: ManagedNode, wanted: object) -> str:
    """Set it, or clear it with None or ""; anything else (false, 0, "none") is refused."""
    if wanted is None:
        wanted = ""
    allowed = [value for value, _ in ManagedNode._meta.get_field("desired_state").choices]
    if not isinstance(wanted, str) or wanted not in allowed:
        raise Refusal("invalid_field", "desired_state must be unconfigured, inactive, active or null.")
    node.desired_state = wanted
    node.save(update_fields=["desired_state"])
    return wanted
