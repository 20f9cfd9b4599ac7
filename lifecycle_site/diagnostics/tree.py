"""A robot's statuses as a tree by name path ("/Robot/Sensors/Lidar" under "/Robot/Sensors" under
"/Robot", as diagnostic_aggregator names them; a name without "/" is a root of its own), each
branch showing the worst of itself and what is below it, and the robot's counts per level."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable

from lifecycle_site.diagnostics.models import ERROR, LEVEL_WORDS, OK, STALE, WARN, Status

# Worst first when branches are summed up: an error outranks not knowing (stale), which outranks a warning.
RANK = {OK: 0, WARN: 1, STALE: 2, ERROR: 3}


def worst(levels: Iterable[int]) -> int:
    return max(levels, key=lambda level: RANK.get(level, 3), default=OK)


@dataclass
class Branch:
    path: str  # the status name it stands for (or would)
    label: str
    depth: int
    status: Status | None = None
    children: dict[str, Branch] = field(default_factory=dict)
    shown: int = OK

    @property
    def word(self) -> str:
        return LEVEL_WORDS.get(self.shown, "ERROR")

    def below(self) -> int:
        return sum(1 + child.below() for child in self.children.values())


def _parts(name: str) -> list[str]:
    return [p for p in name.split("/") if p] if "/" in name else [name]


def build(statuses: Iterable[Status]) -> list[Branch]:
    roots: dict[str, Branch] = {}
    for status in statuses:
        parts = _parts(status.name) or [status.name]
        level, path = roots, ""
        branch = None
        for depth, part in enumerate(parts):
            path = f"{path}/{part}" if "/" in status.name else part
            branch = level.get(part)
            if branch is None:
                branch = level[part] = Branch(path, part, depth)
            level = branch.children
        branch.status = status
    ordered = sorted(roots.values(), key=lambda b: b.label.lower())
    for root in ordered:
        _sum_up(root)
    return ordered


def _sum_up(branch: Branch) -> int:
    own = [branch.status.shown] if branch.status is not None else []
    branch.shown = worst(own + [_sum_up(child) for child in branch.children.values()])
    return branch.shown


def rows(roots: list[Branch]) -> list[Branch]:
    """Depth first, children by name: the order a page lists them in."""
    found: list[Branch] = []

    def walk(branch: Branch) -> None:
        found.append(branch)
        for child in sorted(branch.children.values(), key=lambda b: b.label.lower()):
            walk(child)

    for root in roots:
        walk(root)
    return found


def counts(statuses: Iterable[Status]) -> dict[str, int]:
    found = {word: 0 for word in LEVEL_WORDS.values()}
    for status in statuses:
        found[status.word] += 1
    return found


def as_dicts(branches: list[Branch]) -> list[dict]:
    """The rows as the API and the CLI's --json give them."""
    return [{"path": b.path, "label": b.label, "depth": b.depth, "shown": b.word,
             "status": b.status.as_dict() if b.status else None} for b in branches]
