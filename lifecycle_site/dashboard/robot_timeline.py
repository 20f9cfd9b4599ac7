"""A robot's state timeline: each of its nodes over one window (dashboard/timeline.py), read
together in a bounded number of queries whatever the robot's size: its nodes with their last
record before the window, at most MAX_ROWS_ROBOT records and MAX_ABSENCES_ROBOT absences of the
window (newest first) and one count per node and outcome.
"""
from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

from django.db.models import Count, OuterRef, Subquery

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.dashboard.timeline import (
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
    build,
    later,
    overlapping,
    read_newest,
    window_bounds,
)
from lifecycle_site.fleet.models import ManagedNode, NodeAbsence, Robot


@dataclass
class RobotTimeline:
    robot: Robot
    window: str
    start: datetime
    end: datetime
    nodes: list[Timeline]
    cut_before: datetime | None

    @property
    def availability(self) -> float | None:
        """Time in the desired state over all nodes that have one, 0-1."""
        wanted = [t for t in self.nodes if t.desired]
        if not wanted:
            return None
        return sum(t.availability or 0.0 for t in wanted) / len(wanted)

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
            "nodes": [t.as_dict() for t in self.nodes],
        }


def robot_timeline(robot: Robot, window: str = DEFAULT_WINDOW, now: datetime | None = None,
                   cap: int = MAX_ROWS_ROBOT, absence_cap: int = MAX_ABSENCES_ROBOT) -> RobotTimeline:
    start, end = window_bounds(window, now)
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
        build(node, window, start, end, before.get(node.pk), by_node.get(node.pk, []), cut_before,
              outcomes.get(node.pk, {}), away_by_node.get(node.pk, ()))
        for node in nodes
    ]
    return RobotTimeline(robot, window, start, end, timelines, cut_before)
