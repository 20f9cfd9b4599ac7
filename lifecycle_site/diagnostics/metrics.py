"""The diagnostics families of ``GET /metrics`` (yielded by monitoring.metrics.FleetCollector): a
gauge per status (its shown level, 0 OK to 3 stale), bounded to SERIES_LIMIT series, the worst
first, with how many were left out; counts per robot and level (never left out), and the statuses
not kept at all (over the bounds per robot)."""
from __future__ import annotations

from typing import Iterator

from django.db.models import Case, Count, IntegerField, Q, Value, When
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

from lifecycle_site.diagnostics.models import ERROR, LEVEL_WORDS, OK, STALE, WARN, Intake, Status

SERIES_LIMIT = 2000  # per-status series one scrape gives (a scrape of 10,000 statuses would burden Prometheus)


def families() -> Iterator[Metric]:
    level = GaugeMetricFamily(
        "lifecycle_diagnostic_level", "A diagnostic status's level: 0 OK, 1 WARN, 2 ERROR, 3 stale (not heard "
        f"for the stale time, or STALE). At most {SERIES_LIMIT} series, the worst first.", labels=["robot", "name"])
    shown = Case(When(stale=True, then=Value(STALE)), default="level", output_field=IntegerField())
    worst_first = Case(When(Q(stale=False, level=ERROR), then=Value(0)), When(Q(stale=True) | Q(level=STALE),
                       then=Value(1)), When(level=WARN, then=Value(2)), default=Value(3), output_field=IntegerField())
    rows = (Status.objects.filter(robot__enabled=True).annotate(shown_level=shown, rank=worst_first)
            .order_by("rank", "robot__name", "name").values_list("robot__name", "name", "shown_level"))
    for robot, name, value in rows[:SERIES_LIMIT]:
        level.add_metric([robot, name], value)
    yield level
    counts = GaugeMetricFamily("lifecycle_diagnostic_statuses", "Diagnostic statuses per robot and shown level.",
                               labels=["robot", "level"])
    found: dict[tuple[str, str], int] = {}
    for robot, value, n in (Status.objects.filter(robot__enabled=True).annotate(shown_level=shown)
                            .values_list("robot__name", "shown_level").annotate(n=Count("id")).order_by()):
        key = (robot, LEVEL_WORDS.get(value, "ERROR").lower())
        found[key] = found.get(key, 0) + n
    for robot in {r for r, _ in found}:
        for word in (LEVEL_WORDS[v].lower() for v in (OK, WARN, ERROR, STALE)):
            found.setdefault((robot, word), 0)
    left_out = GaugeMetricFamily("lifecycle_diagnostic_series_left_out", "Statuses without a "
                                 f"lifecycle_diagnostic_level series in this scrape (over {SERIES_LIMIT}).")
    left_out.add_metric([], max(0, sum(found.values()) - SERIES_LIMIT))  # (the counts hold every status)
    yield left_out
    for labels, n in sorted(found.items()):
        counts.add_metric(list(labels), n)
    yield counts
    dropped = CounterMetricFamily("lifecycle_diagnostic_statuses_not_kept",
                                  "Diagnostic statuses not kept (over the statuses per robot), by where.",
                                  labels=["robot", "where"])
    for robot, gateway, here in Intake.objects.values_list("robot__name", "left_out_by_gateway", "left_out_here"):
        dropped.add_metric([robot, "gateway"], gateway)
        dropped.add_metric([robot, "site"], here)
    yield dropped
