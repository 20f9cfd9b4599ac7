"""The alert rules every installation has: without "Desired state not kept", a node's policy
"alert" (docs/modes.md) would alert nobody; "Mode not ready" says when a robot's current mode has
not met its readiness for a minute. Made after every migrate (as the roles are: a fresh database,
a test database after a flush and an upgraded installation all have them); an admin scopes them,
gives them receivers or turns them off (a deleted one comes back with the next upgrade)."""
from __future__ import annotations

from typing import Any

INSTALLED_RULES = (
    ("Desired state not kept", "not_kept", 5.0),
    ("Mode not ready", "mode_not_ready", 60.0),
)


def ensure_installed_rules(**_: Any) -> None:
    from lifecycle_site.alerts.models import Rule

    for name, kind, seconds in INSTALLED_RULES:
        Rule.objects.get_or_create(name=name, defaults={"kind": kind, "for_seconds": seconds})
