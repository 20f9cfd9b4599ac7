"""What ``GET /metrics`` tells Prometheus, read from the database and the gateways' heartbeats
at each scrape (nothing is kept in this process, so every site instance answers the same).

Counters come from append-only records and from the gateways' own counters, so they only
grow; the transition latency histogram is counted from the audit log in one query.
"""
from __future__ import annotations

import time
from typing import Iterator

from django.db.models import Count, Q, Sum
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.registry import Collector
from prometheus_client.utils import floatToGoString

from lifecycle_site.alerts import metrics as alert_metrics
from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.diagnostics import metrics as diagnostic_metrics
from lifecycle_site.fleet.models import Gateway, GroupRun, ManagedNode
from lifecycle_site.gateway_link import gateways
from lifecycle_site.modes import drift, readiness
from lifecycle_site.modes.models import CurrentMode
from ros_gateway.shared import operations

# Seconds; a lifecycle transition takes milliseconds to a node's own timeout (at most 25 s here).
DURATION_BUCKETS_S = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
NOT_RUNNING = "not_running"
MODE_ROBOTS_LIMIT = 500  # robots whose drift one scrape works out


class FleetCollector(Collector):
    def collect(self) -> Iterator[Metric]:
        yield from self.nodes()
        yield from self.gateways()
        yield from self.transitions()
        yield from self.runs()
        yield from self.modes()
        yield from alert_metrics.families()
        yield from diagnostic_metrics.families()

    @staticmethod
    def nodes() -> Iterator[Metric]:
        family = GaugeMetricFamily(
            "lifecycle_nodes", f"Managed nodes by robot and lifecycle state ({NOT_RUNNING}: not in the ROS graph).",
            labels=["gateway", "robot", "state"],
        )
        rows = (ManagedNode.objects.values("robot__gateway__name", "robot__name", "alive", "state_label")
                .annotate(n=Count("id")).order_by())
        counts: dict[tuple[str, str, str], int] = {}
        for row in rows:
            state = (row["state_label"] or "unknown") if row["alive"] else NOT_RUNNING
            key = (row["robot__gateway__name"], row["robot__name"], state)
            counts[key] = counts.get(key, 0) + row["n"]
        for labels, count in sorted(counts.items()):
            family.add_metric(list(labels), count)
        yield family

    @staticmethod
    def gateways() -> Iterator[Metric]:
        rows = list(Gateway.objects.order_by("name"))
        online = GaugeMetricFamily("lifecycle_gateway_online", "1 while the gateway's heartbeat is fresh.",
                                   labels=["gateway"])
        age = GaugeMetricFamily("lifecycle_gateway_heartbeat_age_seconds",
                                "Seconds since the gateway's last heartbeat (absent if it never beat).",
                                labels=["gateway"])
        backlog = GaugeMetricFamily("lifecycle_gateway_backlog", "Entries of the gateway's streams not yet stored.",
                                    labels=["gateway"])
        quarantined = GaugeMetricFamily("lifecycle_gateway_quarantined",
                                        "1 while the site has the gateway cut off (see the fleet page for why).",
                                        labels=["gateway"])
        redis_bytes = GaugeMetricFamily("lifecycle_gateway_redis_bytes",
                                        "Bytes the gateway's Redis keys held at the site's last count.",
                                        labels=["gateway"])
        counters = {
            "quarantines": CounterMetricFamily("lifecycle_gateway_quarantines",
                                               "Times the site cut the gateway off.", labels=["gateway"]),
            "live_refused": CounterMetricFamily("lifecycle_gateway_live_refused",
                                                "Live updates of the gateway the site refused.", labels=["gateway"]),
            "facts_lost": CounterMetricFamily("lifecycle_gateway_facts_lost",
                                              "Facts trimmed from Redis before the site stored them.",
                                              labels=["gateway"]),
            "facts_rejected": CounterMetricFamily("lifecycle_gateway_facts_rejected",
                                                  "Facts the site could not apply.", labels=["gateway"]),
            "logs_received": CounterMetricFamily("lifecycle_log_records_received",
                                                 "Log records stored from the gateway.", labels=["gateway"]),
            "logs_dropped": CounterMetricFamily("lifecycle_log_records_dropped",
                                                "Log records the gateway's buffer dropped.", labels=["gateway"]),
            "logs_lost": CounterMetricFamily("lifecycle_log_batches_lost",
                                             "Log batches trimmed from Redis before the site stored them.",
                                             labels=["gateway"]),
        }
        now = time.time()
        for row, state in zip(rows, gateways.statuses(rows), strict=True):
            online.add_metric([row.name], 1 if state.online else 0)
            if state.last_beat is not None:
                age.add_metric([row.name], max(now - state.last_beat.timestamp(), 0.0))
            backlog.add_metric([row.name], row.backlog)
            quarantined.add_metric([row.name], 1 if state.state == gateways.QUARANTINED else 0)
            redis_bytes.add_metric([row.name], row.redis_bytes)
            for field, family in counters.items():
                family.add_metric([row.name], getattr(row, field))
        yield from (online, age, backlog, quarantined, redis_bytes, *counters.values())

    @staticmethod
    def transitions() -> Iterator[Metric]:
        total = CounterMetricFamily("lifecycle_transitions", "Transition attempts in the audit log.",
                                    labels=["outcome", "source"])
        for row in TransitionRecord.objects.values("outcome", "source").annotate(n=Count("id")).order_by():
            total.add_metric([row["outcome"], row["source"]], row["n"])
        yield total
        # Attempts that reached a node (observed changes made elsewhere carry no duration).
        timed = TransitionRecord.objects.filter(duration_ms__isnull=False).exclude(
            outcome__in=(TransitionRecord.Outcome.REJECTED, TransitionRecord.Outcome.OBSERVED))
        counts = timed.aggregate(
            total=Count("id"), total_ms=Sum("duration_ms"),
            **{f"le_{i}": Count("id", filter=Q(duration_ms__lte=b * 1000)) for i, b in enumerate(DURATION_BUCKETS_S)},
        )
        buckets = [(floatToGoString(b), counts[f"le_{i}"]) for i, b in enumerate(DURATION_BUCKETS_S)]
        yield HistogramMetricFamily(
            "lifecycle_transition_duration_seconds", "How long transitions that reached a node took.",
            buckets=[*buckets, ("+Inf", counts["total"])], sum_value=(counts["total_ms"] or 0.0) / 1000,
        )

    @staticmethod
    def runs() -> Iterator[Metric]:
        family = GaugeMetricFamily("lifecycle_group_runs_active", "Group runs queued or running.",
                                   labels=["status"])
        active = dict(GroupRun.objects.filter(status__in=(GroupRun.Status.QUEUED, GroupRun.Status.RUNNING))
                      .values_list("status").annotate(n=Count("id")).order_by())
        for status in (GroupRun.Status.QUEUED, GroupRun.Status.RUNNING):
            family.add_metric([status], active.get(status, 0))
        yield family
        # Runs are never deleted, so the ended ones only grow: a counter (rate() of failed runs).
        ended = CounterMetricFamily("lifecycle_group_runs_ended", "Group runs ended, by operation and verdict.",
                                    labels=["operation", "status"])
        rows = GroupRun.objects.filter(status__in=GroupRun.ENDED).values("operation", "status").annotate(n=Count("id"))
        counts = {(row["operation"], row["status"]): row["n"] for row in rows.order_by()}
        # Every operation and verdict, 0 until one ends so (a series that appears late hides its first increase).
        for operation in sorted({name for name, _ in operations.choices()} | {op for op, _ in counts}):
            for status in GroupRun.ENDED:
                ended.add_metric([operation, status], counts.get((operation, status), 0))
        yield ended

    @staticmethod
    def modes() -> Iterator[Metric]:
        """Per robot in a mode, how many of its nodes differ from it (state, parameter or not running)."""
        family = GaugeMetricFamily("lifecycle_mode_drift", "Differences between a robot and its current mode "
                                   f"(robots in a mode; at most {MODE_ROBOTS_LIMIT}).", labels=["robot", "mode"])
        ready = GaugeMetricFamily("lifecycle_mode_ready", "1 while every readiness predicate of the robot's current "
                                  "mode holds (modes without predicates: 1).", labels=["robot", "mode"])
        current = CurrentMode.objects.select_related("robot", "mode", "applied_by", "run").order_by("robot__name")
        for now_mode in current[:MODE_ROBOTS_LIMIT]:
            labels = [now_mode.robot.name, now_mode.mode.name]
            family.add_metric(labels, len(drift.differences(now_mode.robot, now_mode)))
            ready.add_metric(labels, 1 if readiness.evaluate(now_mode)["ready"] else 0)
        yield family
        yield ready

