"""Layout of the lifecycle state machine drawn as SVG on the node page (thesis fig. 2.5)."""
from __future__ import annotations

import math
from dataclasses import dataclass

from ros_gateway.shared import state_machine as sm

WIDTH, HEIGHT = 720, 360
BOX_W, BOX_H = 112, 34
EDGE_GAP = 5

# Primary states in the middle row, transition states above and below, the end at the bottom.
POSITIONS: dict[int, tuple[int, int]] = {
    sm.UNCONFIGURED: (80, 150),
    sm.INACTIVE: (360, 150),
    sm.ACTIVE: (640, 150),
    sm.CONFIGURING: (220, 50),
    sm.CLEANINGUP: (220, 250),
    sm.ACTIVATING: (500, 50),
    sm.DEACTIVATING: (500, 250),
    sm.ERRORPROCESSING: (80, 325),
    sm.SHUTTINGDOWN: (360, 325),
    sm.FINALIZED: (640, 325),
}


@dataclass
class Box:
    state_id: int
    label: str
    x: float
    y: float
    primary: bool
    current: bool


@dataclass
class Edge:
    label: str
    x1: float
    y1: float
    x2: float
    y2: float
    external: bool
    error: bool
    available: bool  # may be requested from the current state

    @property
    def label_x(self) -> float:
        return (self.x1 + self.x2) / 2

    @property
    def label_y(self) -> float:
        return (self.y1 + self.y2) / 2 - 4


def _clip(x1: float, y1: float, x2: float, y2: float) -> tuple[float, float]:
    """Where the line from (x1, y1) to (x2, y2) enters the box centred on (x2, y2)."""
    dx, dy = x2 - x1, y2 - y1
    if dx == dy == 0:
        return x2, y2
    scale = min(
        (BOX_W / 2 + 4) / abs(dx) if dx else math.inf,
        (BOX_H / 2 + 4) / abs(dy) if dy else math.inf,
    )
    return x2 - dx * scale, y2 - dy * scale


def layout(current_state: int, alive: bool = True) -> dict:
    boxes = [
        Box(state_id, sm.state_label(state_id), x, y, sm.is_primary(state_id), state_id == current_state)
        for state_id, (x, y) in POSITIONS.items()
    ]
    available = {t.id for t in sm.valid_transitions(current_state)} if alive else set()
    edges = []
    for transition in sm.TRANSITIONS:
        (x1, y1), (x2, y2) = POSITIONS[transition.start], POSITIONS[transition.goal]
        # Shift each edge a little to its right, so an edge and its way back stay apart.
        length = math.hypot(x2 - x1, y2 - y1)
        nx, ny = -(y2 - y1) / length * EDGE_GAP, (x2 - x1) / length * EDGE_GAP
        x1, y1, x2, y2 = x1 + nx, y1 + ny, x2 + nx, y2 + ny
        sx, sy = _clip(x2, y2, x1, y1)
        ex, ey = _clip(x1, y1, x2, y2)
        edges.append(
            Edge(
                transition.label if transition.external else "",
                sx, sy, ex, ey,
                transition.external,
                transition.goal == sm.ERRORPROCESSING,
                transition.id in available,
            )
        )
    return {"width": WIDTH, "height": HEIGHT, "box_w": BOX_W, "box_h": BOX_H, "boxes": boxes, "edges": edges}
