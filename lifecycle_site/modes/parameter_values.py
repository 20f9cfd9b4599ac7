"""What a node's parameters are known to be while its robot is in a mode: what the mode's run set
(its records, whatever the gateway's clock says) and any change recorded since the mode was
applied (by anyone: the audit log's parameter records). A value not recorded since is not known
to be the mode's; after a new process of the node, only what was recorded since it started."""
from __future__ import annotations

from typing import Any

from django.db.models import Q
from django.utils.translation import gettext_noop

from lifecycle_site.audit.models import ParameterRecord
from lifecycle_site.fleet.models import ManagedNode
from lifecycle_site.modes.models import CurrentMode

# Kept in English (code compares them; the API gives them as they are); drift.py words them in the reader's language.
NOT_SET = gettext_noop("not set since the mode was applied")
UNKNOWN = gettext_noop("unknown: its process was restarted")


def known(now_mode: CurrentMode, node: ManagedNode, names: list[str]) -> dict[str, Any]:
    """name -> the value last recorded, or NOT_SET / UNKNOWN (in the order of ``names``)."""
    if not names:
        return {}
    restarted = (node.process_status == "restarted" and node.process_since is not None
                 and node.process_since > now_mode.since)
    if restarted:
        values: dict[str, Any] = dict.fromkeys(names, UNKNOWN)
        since = Q(at__gte=node.process_since)
    else:
        values = dict.fromkeys(names, NOT_SET)
        since = Q(at__gte=now_mode.since) | (Q(run_id=now_mode.run_id) if now_mode.run_id else Q(pk__in=[]))
    for name, value in (ParameterRecord.objects.filter(node=node, name__in=names, outcome__in=("succeeded", "observed"))
                        .filter(since).order_by("at", "id").values_list("name", "new_value")):
        values[name] = value
    return values
