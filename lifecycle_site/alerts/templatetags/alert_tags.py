"""``{% alert_count %}``: the header's link to the alerts page with the count of firing alerts."""
from __future__ import annotations

from django import template

from lifecycle_site.alerts import lifecycle

register = template.Library()


@register.inclusion_tag("alerts/_header.html", takes_context=True)
def alert_count(context) -> dict:
    user = context.get("user")
    shown = user is not None and user.is_authenticated and user.has_perm(lifecycle.VIEW_PERMISSION)
    return {"shown": shown, "alert_counts": lifecycle.counts() if shown else {}}
