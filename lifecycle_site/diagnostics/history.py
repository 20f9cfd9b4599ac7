"""A status's level over time, from its level changes: as a list, and as a lane of segments over a
window (drawn beside the node timeline and on the status's page)."""
from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from typing import Any

from django.db.models import OuterRef, Subquery

from lifecycle_site.diagnostics.models import LEVEL_WORDS, LevelChange, Status

LANES = 20  # statuses drawn beside one node's timeline


@dataclass(frozen=True)
class Segment:
    start: datetime
    end: datetime
    level: int
    message: str
    left: float  # per cent of the window
    width: float

    @property
    def word(self) -> str:
        return LEVEL_WORDS.get(self.level, "ERROR")


def lane(robot: Any, name: str, start: datetime, end: datetime) -> list[Segment]:
    """The levels a status showed within [start, end): the change before the window opens it."""
    before = (LevelChange.objects.filter(robot=robot, name=name, at__lte=start).order_by("-at", "-id")
              .values_list("at", "level", "message").first())
    inside = list(LevelChange.objects.filter(robot=robot, name=name, at__gt=start, at__lt=end)
                  .order_by("at", "id").values_list("at", "level", "message"))
    return _segments(([(start, before[1], before[2])] if before else []) + inside, start, end)


def _segments(changes: list[tuple[datetime, int, str]], start: datetime, end: datetime) -> list[Segment]:
    span = (end - start).total_seconds() or 1.0
    segments = []
    for index, (at, level, message) in enumerate(changes):
        until = changes[index + 1][0] if index + 1 < len(changes) else end
        if until <= at:
            continue
        left = (max(at, start) - start).total_seconds() / span * 100
        width = (until - max(at, start)).total_seconds() / span * 100
        segments.append(Segment(max(at, start), until, level, message, round(left, 3), round(max(width, 0.2), 3)))
    return segments


def node_lanes(robot: Any, node_name: str, start: datetime, end: datetime) -> list[dict]:
    """The lanes of the statuses a node reports (at most LANES), for its timeline page: two queries
    however many (the statuses with the level each had when the window opened, the changes inside)."""
    earlier = LevelChange.objects.filter(robot=OuterRef("robot"), name=OuterRef("name"), at__lte=start).order_by(
        "-at", "-id")
    rows = list(Status.objects.filter(robot=robot, node=node_name).order_by("name").annotate(
        before_level=Subquery(earlier.values("level")[:1]), before_message=Subquery(earlier.values("message")[:1]))
        .values_list("name", "before_level", "before_message")[:LANES])
    inside: dict[str, list] = {name: [] for name, _, _ in rows}
    for name, at, level, message in (LevelChange.objects.filter(robot=robot, name__in=list(inside), at__gt=start,
                                                                at__lt=end)
                                     .order_by("at", "id").values_list("name", "at", "level", "message")):
        inside[name].append((at, level, message))
    return [{"name": name, "segments": _segments(([(start, level, message)] if level is not None else [])
                                                  + inside[name], start, end)}
            for name, level, message in rows]


def changes(robot: Any, name: str, limit: int = 200) -> list[LevelChange]:
    return list(LevelChange.objects.filter(robot=robot, name=name).order_by("-at", "-id")[:limit])
