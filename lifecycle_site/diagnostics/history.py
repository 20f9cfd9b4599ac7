"""A status's level over time, from its level changes: as a list, and as a lane of segments over a
window (drawn beside the node timeline and on the status's page)."""
from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from typing import Any

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
    changes = ([(start, before[1], before[2])] if before else []) + inside
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
    """The lanes of the statuses a node reports (at most LANES), for its timeline page."""
    names = list(Status.objects.filter(robot=robot, node=node_name).order_by("name")
                 .values_list("name", flat=True)[:LANES])
    return [{"name": name, "segments": lane(robot, name, start, end)} for name in names]


def changes(robot: Any, name: str, limit: int = 200) -> list[LevelChange]:
    return list(LevelChange.objects.filter(robot=robot, name=name).order_by("-at", "-id")[:limit])
