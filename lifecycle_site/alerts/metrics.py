"""The alert families of ``GET /metrics`` (yielded by monitoring.metrics.FleetCollector)."""
from __future__ import annotations

from typing import Iterator

from django.db.models import Count
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

from lifecycle_site.alerts.models import Alert, Receiver, Rule


def families() -> Iterator[Metric]:
    firing = GaugeMetricFamily(
        "lifecycle_alerts_firing", "Alerts not yet resolved, by rule and status (firing, or acknowledged).",
        labels=["rule", "status"],
    )
    counts = {(r, s): n for r, s, n in Alert.objects.filter(status__in=Alert.ACTIVE)
              .values_list("rule_name", "status").annotate(n=Count("id")).order_by()}
    # Every enabled rule shows 0 when quiet, so a dashboard sees the series before the first alert.
    for name in Rule.objects.filter(enabled=True).values_list("name", flat=True):
        for status in Alert.ACTIVE:
            counts.setdefault((name, status), 0)
    for (rule, status), n in sorted(counts.items()):
        firing.add_metric([rule, status], n)
    yield firing
    sent = CounterMetricFamily(
        "lifecycle_alert_notifications", "Alert notifications by receiver and outcome (delivered; failed "
        "after every retry; dropped because the delivery queue was full).", labels=["receiver", "outcome"],
    )
    for name, delivered, failed, dropped in Receiver.objects.values_list("name", "delivered", "failed", "dropped"):
        for outcome, n in (("delivered", delivered), ("failed", failed), ("dropped", dropped)):
            sent.add_metric([name, outcome], n)
    yield sent
