"""A robot's state timeline: each of its nodes over one window (timelines/node.py), read
together in a bounded number of queries whatever the robot's size: its nodes with their last
record before the window, at most MAX_ROWS_ROBOT records and MAX_ABSENCES_ROBOT absences of the
window (newest first) and one count per node and outcome.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime

from django.db.models import Count, OuterRef, Subquery

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import ManagedNode, NodeAbsence, Robot
from lifecycle_site.timelines.events import MAX_EVENTS_ROBOT, Event, outage_events, record_events
from lifecycle_site.timelines.node import (
    ABSENCE_FIELDS,
    DEFAULT_WINDOW,
    FAILURE_OUTCOMES,
    MAX_ABSENCES_ROBOT,
    MAX_ROWS_ROBOT,
    RESTART_OUTCOMES,
    ROW_FIELDS,
    Absence,
    Row,
    Timeline,
    Window,
    as_window,
    build,
    later,
    overlapping,
    read_newest,
)


@dataclass
class RobotTimeline:
    robot: Robot
    window: str
    start: datetime
    end: datetime
    nodes: list[Timeline]
    cut_before: datetime | None
    outages: list[Event] = field(default_factory=list)  # its gateway's, in the window

    @property
    def availability(self) -> float | None:
        """The mean of its nodes' availabilities (those with a desired state, seen in the window), 0-1."""
        found = [t.availability for t in self.nodes if t.availability is not None]
        if not found:
            return None
        return sum(found) / len(found)

    @property
    def events(self) -> list[Event]:
        """Its nodes' marked records, oldest first."""
        return sorted((e for t in self.nodes for e in t.events), key=lambda e: e.at)

    @property
    def failures(self) -> int:
        return sum(t.failures for t in self.nodes)

    @property
    def restarts(self) -> int:
        return sum(t.restarts for t in self.nodes)

    def as_dict(self) -> dict:
        availability = self.availability
        return {
            "robot": self.robot.name,
            "window": {"name": self.window, "start": self.start.isoformat(), "end": self.end.isoformat()},
            "availability_percent": None if availability is None else round(100 * availability, 3),
            "failures": self.failures,
            "restarts": self.restarts,
            "not_read_before": self.cut_before.isoformat() if self.cut_before else None,
            "gateway_outages": [e.as_dict() for e in self.outages],
            "nodes": [t.as_dict() for t in self.nodes],
        }


def robot_timeline(robot: Robot, window: str | Window = DEFAULT_WINDOW, now: datetime | None = None,
                   cap: int = MAX_ROWS_ROBOT, absence_cap: int = MAX_ABSENCES_ROBOT) -> RobotTimeline:
    window = as_window(window, now)
    start, end = window.start, window.end
    last_before = TransitionRecord.objects.filter(node=OuterRef("pk"), requested_at__lt=start).order_by(
        "-requested_at")
    nodes = list(ManagedNode.objects.filter(robot=robot).select_related("robot").annotate(
        before_id=Subquery(last_before.values("id")[:1])))
    inside = TransitionRecord.objects.filter(robot_name=robot.name, requested_at__gte=start, requested_at__lte=end)
    values, cut_before = read_newest(inside.values_list("node_id", *ROW_FIELDS), ROW_FIELDS, cap)
    by_node: dict[int, list[Row]] = {}
    for node_id, *rest in values:
        by_node.setdefault(node_id, []).append(Row(*rest))
    away, absences_cut = read_newest(overlapping(
        NodeAbsence.objects.filter(node_id__in=[n.pk for n in nodes]), start, end
    ).values_list("node_id", *ABSENCE_FIELDS), ABSENCE_FIELDS, absence_cap)
    cut_before = later(cut_before, absences_cut)
    away_by_node: dict[int, list[Absence]] = {}
    for node_id, *rest in away:
        away_by_node.setdefault(node_id, []).append(Absence(*rest))
    before: dict[int, Row] = {}
    if cut_before is None:
        ids = [n.before_id for n in nodes if n.before_id is not None]
        for node_id, *rest in TransitionRecord.objects.filter(id__in=ids).values_list("node_id", *ROW_FIELDS):
            before[node_id] = Row(*rest)
    outcomes: dict[int, dict[str, int]] = {}
    counted = inside.filter(outcome__in=(*FAILURE_OUTCOMES, *RESTART_OUTCOMES)).order_by()
    for node_id, outcome, n in counted.values_list("node_id", "outcome").annotate(n=Count("id")):
        outcomes.setdefault(node_id, {})[outcome] = n
    timelines = [
        build(node, window.name, start, end, before.get(node.pk), by_node.get(node.pk, []), cut_before,
              outcomes.get(node.pk, {}), away_by_node.get(node.pk, ()))
        for node in nodes
    ]
    events = record_events(((t.node, r.requested_at, r.outcome, r.id) for t in timelines
                            for r in by_node.get(t.node.pk, [])), MAX_EVENTS_ROBOT)
    for timeline in timelines:
        timeline.events = [e for e in events if e.node is timeline.node]
    return RobotTimeline(robot, window.name, start, end, timelines, cut_before, outage_events(robot, start, end))
