"""What people do to an alert: acknowledge it (the pages and the API share this)."""
from __future__ import annotations

from datetime import timedelta

from django.db.models import Count, Q, QuerySet
from django.utils import timezone
from django.utils.translation import gettext as _

from lifecycle_site.alerts.models import Alert
from lifecycle_site.refusal import Refusal

ACKNOWLEDGE_PERMISSION = "alerts.acknowledge_alert"
VIEW_PERMISSION = "alerts.view_alert"


def acknowledge(alert_id: int, user) -> Alert:
    """Mark a firing alert acknowledged by ``user`` (no further action: its receivers are told
    when it resolves). Acknowledging it again is refused, naming who did it first."""
    updated = Alert.objects.filter(pk=alert_id, status=Alert.Status.FIRING).update(
        status=Alert.Status.ACKNOWLEDGED, acknowledged_at=timezone.now(), acknowledged_by=user,
        acknowledged_by_name=user.get_username(),
    )
    alert = Alert.objects.select_related("rule").filter(pk=alert_id).first()
    if alert is None:
        raise Refusal("not_found", _("There is no alert %(id)s.") % {"id": alert_id}, 404)
    if not updated:
        if alert.status == Alert.Status.ACKNOWLEDGED:
            if alert.acknowledged_by_name:
                message = _("Alert %(id)s was acknowledged already by %(user)s.") % {
                    "id": alert_id, "user": alert.acknowledged_by_name}
            else:
                message = _("Alert %(id)s was acknowledged already by a deleted user.") % {"id": alert_id}
            raise Refusal("already_acknowledged", message, 409)
        raise Refusal("already_resolved", _("Alert %(id)s is resolved already: its condition is over; "
                                            "nothing to acknowledge.") % {"id": alert_id}, 409)
    return alert


def counts() -> dict[str, int]:
    """Active alerts: firing (nobody acknowledged them yet) and acknowledged."""
    found = dict(Alert.objects.filter(status__in=Alert.ACTIVE).values_list("status").annotate(n=Count("id"))
                 .order_by())
    return {"firing": found.get(Alert.Status.FIRING, 0), "acknowledged": found.get(Alert.Status.ACKNOWLEDGED, 0)}


# The alerts page's default view keeps an alert this long after it resolved: one that resolves
# while the page is open changes its status in place instead of vanishing without a word.
RECENTLY_RESOLVED_S = 3600


def listed(status: str) -> QuerySet[Alert]:
    """Alerts by status: 'active' (firing or acknowledged), 'recent' (active, and resolved within
    RECENTLY_RESOLVED_S), one status, or 'all'."""
    alerts = Alert.objects.select_related("rule")
    if status == "active":
        return alerts.filter(status__in=Alert.ACTIVE)
    if status == "recent":
        since = timezone.now() - timedelta(seconds=RECENTLY_RESOLVED_S)
        return alerts.filter(Q(status__in=Alert.ACTIVE) | Q(status=Alert.Status.RESOLVED, resolved_at__gte=since))
    if status in Alert.Status.values:
        return alerts.filter(status=status)
    return alerts
