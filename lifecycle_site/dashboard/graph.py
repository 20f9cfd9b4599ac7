"""Layout of the lifecycle state machine drawn as SVG on the node page (thesis fig. 2.5).

Two drawings of the same machine: a wide one (primary states in a row) and a tall one for
phones (primary states in a column), where the wide one, scaled to a 390 px screen, would
leave its labels about 5 px high. Edges are polylines: where a straight line would cross a
box that is not one of its ends, the drawing routes it around through waypoints
(tests/unit/test_graph.py checks that no edge crosses a box and no label covers one).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from ros_gateway.shared import state_machine as sm

EDGE_GAP = 5
Point = tuple[float, float]


@dataclass(frozen=True)
class Plan:
    """Where one drawing puts each state, and the waypoints of the edges routed around boxes."""

    name: str
    width: int
    height: int
    box_w: int
    box_h: int
    positions: dict[int, Point]
    # transition id -> points between its start and goal boxes
    waypoints: dict[int, tuple[Point, ...]] = field(default_factory=dict)
    # transition id -> where its label goes (default: middle of the edge's first segment)
    label_at: dict[int, Point] = field(default_factory=dict)


S = sm
WIDE = Plan(
    "wide", 720, 360, 112, 34,
    {
        S.UNCONFIGURED: (80, 150), S.INACTIVE: (360, 150), S.ACTIVE: (640, 150),
        S.CONFIGURING: (220, 50), S.ACTIVATING: (500, 50),
        S.CLEANINGUP: (220, 250), S.SHUTTINGDOWN: (360, 250), S.DEACTIVATING: (500, 250),
        S.ERRORPROCESSING: (80, 330), S.FINALIZED: (640, 330),
    },
    waypoints={5: ((200, 192),), 32: ((208, 160),), 42: ((432, 272),), 52: ((296, 272),)},
    label_at={4: (604, 214)},  # "deactivate" right of its line, clear of the "shutdown" beside it
)

# Phones: three columns. Edges that would cross a box run down the gaps between the columns:
# left, configuring's error path (x 120) and errorprocessing's way back up (132); right, the
# shutdown paths of inactive (248) and unconfigured (255) and the error paths of cleaningup
# and deactivating (262).
TALL = Plan(
    "tall", 380, 600, 104, 34,
    {
        S.UNCONFIGURED: (190, 40), S.CONFIGURING: (62, 125), S.CLEANINGUP: (318, 125),
        S.INACTIVE: (190, 210), S.ACTIVATING: (62, 295), S.DEACTIVATING: (318, 295),
        S.ACTIVE: (190, 380), S.SHUTTINGDOWN: (190, 470),
        S.ERRORPROCESSING: (62, 560), S.FINALIZED: (318, 560),
    },
    waypoints={
        12: ((120, 150), (120, 535)),
        60: ((132, 540), (132, 62)),
        6: ((248, 222), (248, 452)),
        5: ((255, 48), (255, 458)),
        22: ((262, 140), (262, 520)),
        42: ((262, 300), (262, 520)),
    },
    label_at={5: (306, 60), 6: (218, 262)},
)


@dataclass
class Box:
    state_id: int
    label: str
    x: float
    y: float
    primary: bool
    current: bool
    left: float = 0.0
    top: float = 0.0


@dataclass
class Edge:
    label: str
    points: list[Point]
    external: bool
    error: bool
    available: bool  # may be requested from the current state
    label_x: float = 0.0
    label_y: float = 0.0

    @property
    def points_text(self) -> str:
        return " ".join(f"{x:.0f},{y:.0f}" for x, y in self.points)  # a unit is < 1 px on screen

    # The first and last points, as the one-segment drawing had them.
    @property
    def x1(self) -> float:
        return self.points[0][0]

    @property
    def y1(self) -> float:
        return self.points[0][1]

    @property
    def x2(self) -> float:
        return self.points[-1][0]

    @property
    def y2(self) -> float:
        return self.points[-1][1]


def _clip(plan: Plan, x1: float, y1: float, x2: float, y2: float) -> Point:
    """Where the line from (x1, y1) to (x2, y2) enters the box centred on (x2, y2)."""
    dx, dy = x2 - x1, y2 - y1
    if dx == dy == 0:
        return x2, y2
    scale = min(
        (plan.box_w / 2 + 4) / abs(dx) if dx else math.inf,
        (plan.box_h / 2 + 4) / abs(dy) if dy else math.inf,
    )
    return x2 - dx * scale, y2 - dy * scale


def _route(plan: Plan, transition: sm.Transition) -> list[Point]:
    (x1, y1), (x2, y2) = plan.positions[transition.start], plan.positions[transition.goal]
    middle = list(plan.waypoints.get(transition.id, ()))
    if not middle:
        # Shift a straight edge a little to its right, so it and its way back stay apart.
        length = math.hypot(x2 - x1, y2 - y1)
        nx, ny = -(y2 - y1) / length * EDGE_GAP, (x2 - x1) / length * EDGE_GAP
        x1, y1, x2, y2 = x1 + nx, y1 + ny, x2 + nx, y2 + ny
        return [_clip(plan, x2, y2, x1, y1), _clip(plan, x1, y1, x2, y2)]
    first, last = middle[0], middle[-1]
    return [_clip(plan, *first, x1, y1), *middle, _clip(plan, *last, x2, y2)]


def _edge(plan: Plan, transition: sm.Transition, available: set[int]) -> Edge:
    points = _route(plan, transition)
    edge = Edge(
        transition.label if transition.external else "",
        points,
        transition.external,
        transition.goal == sm.ERRORPROCESSING,
        transition.id in available,
    )
    if transition.id in plan.label_at:
        edge.label_x, edge.label_y = plan.label_at[transition.id]
    else:
        (ax, ay), (bx, by) = points[0], points[1]
        edge.label_x, edge.label_y = (ax + bx) / 2, (ay + by) / 2 - 4
    return edge


def draw(plan: Plan, current_state: int, alive: bool = True) -> dict:
    """One drawing's boxes and edges, the current state and the transitions open now marked."""
    boxes = [
        Box(state_id, sm.state_label(state_id), x, y, sm.is_primary(state_id), state_id == current_state,
            x - plan.box_w / 2, y - plan.box_h / 2)
        for state_id, (x, y) in plan.positions.items()
    ]
    available = {t.id for t in sm.valid_transitions(current_state)} if alive else set()
    edges = [_edge(plan, t, available) for t in sm.TRANSITIONS]
    return {"name": plan.name, "width": plan.width, "height": plan.height, "box_w": plan.box_w,
            "box_h": plan.box_h, "boxes": boxes, "edges": edges}


def layout(current_state: int, alive: bool = True) -> dict:
    """Both drawings, wide first; the page's style sheet shows the one that fits the screen."""
    return {"drawings": [draw(WIDE, current_state, alive), draw(TALL, current_state, alive)]}
