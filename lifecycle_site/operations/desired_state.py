"""The state automatic recovery brings a node back to after its process restarts (the robot's
gateway reads it with its configuration), and whether it is kept there against other tools
(off, alert, enforce: ros_gateway/desired_keeper.py), set from the API and the node page alike."""
from __future__ import annotations

import logging

from django.utils import timezone
from django.utils.translation import gettext as _

from lifecycle_site.fleet.models import ManagedNode
from lifecycle_site.refusal import Refusal
from ros_gateway.shared import protocol

log = logging.getLogger(__name__)


def set_desired_state(node: ManagedNode, wanted: object) -> str:
    """Set it, or clear it with None or ""; anything else (false, 0, "none") is refused."""
    if wanted is None:
        wanted = ""
    allowed = [value for value, _ in ManagedNode._meta.get_field("desired_state").choices]
    if not isinstance(wanted, str) or wanted not in allowed:
        raise Refusal("invalid_field", _("desired_state must be unconfigured, inactive, active or null."))
    node.desired_state = wanted
    node.save(update_fields=["desired_state"])
    return wanted


def set_keep(node: ManagedNode, wanted: object) -> str:
    """The node's own policy (off, alert, enforce), or its robot's with None or ""."""
    if wanted is None:
        wanted = ""
    if not isinstance(wanted, str) or wanted not in ("", *protocol.KEEP_POLICIES):
        raise Refusal("invalid_field", _("keep must be off, alert, enforce or null (as its robot says)."))
    node.keep_desired = wanted
    node.save(update_fields=["keep_desired"])
    return wanted


def resume_keeping(node: ManagedNode, user) -> None:
    """An operator lifts the pause the gateway made after a fight (its config says "enforce" again)."""
    if node.enforcement_stopped is None:
        raise Refusal("not_stopped", _("%(node)s on %(robot)s is not left alone: nothing to resume.") % {
            "node": node.name, "robot": node.robot.name}, 409)
    log.info("%s resumed keeping %s in its desired state", getattr(user, "username", "?"), node.key)
    node.enforcement_stopped, node.enforcement_note, node.enforcement_resumed = None, "", timezone.now()
    node.save(update_fields=["enforcement_stopped", "enforcement_note", "enforcement_resumed"])
