"""The state machine drawings: no edge runs through a box it does not start or end at, and no
label covers a box or another label, in the wide drawing and in the tall one for phones."""
from __future__ import annotations

import pytest

from lifecycle_site.dashboard.graph import layout
from ros_gateway.shared import state_machine as sm

# Label font sizes in drawing units (static/css/site.css) and a generous glyph width.
FONT = {"wide": 11, "tall": 12.5}
GLYPH = 0.62


def crosses(p, q, rect) -> bool:
    """Whether the segment p-q touches the rectangle (xmin, ymin, xmax, ymax) (Liang-Barsky)."""
    (x1, y1), (x2, y2) = p, q
    xmin, ymin, xmax, ymax = rect
    t0, t1 = 0.0, 1.0
    dx, dy = x2 - x1, y2 - y1
    for pp, qq in ((-dx, x1 - xmin), (dx, xmax - x1), (-dy, y1 - ymin), (dy, ymax - y1)):
        if pp == 0:
            if qq < 0:
                return False
        else:
            t = qq / pp
            t0, t1 = (max(t0, t), t1) if pp < 0 else (t0, min(t1, t))
    return t0 <= t1


def box_rect(drawing: dict, box, pad: float = 2) -> tuple:
    w, h = drawing["box_w"], drawing["box_h"]
    return box.x - w / 2 - pad, box.y - h / 2 - pad, box.x + w / 2 + pad, box.y + h / 2 + pad


def label_rect(edge, font: float) -> tuple:
    half = len(edge.label) * font * GLYPH / 2
    return edge.label_x - half, edge.label_y - font * 0.8, edge.label_x + half, edge.label_y + font * 0.25


def segments(edge) -> list:
    return list(zip(edge.points, edge.points[1:], strict=False))


def overlap(a: tuple, b: tuple) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def drawings() -> list[dict]:
    return layout(sm.UNCONFIGURED)["drawings"]


@pytest.mark.parametrize("index", [0, 1], ids=["wide", "tall"])
def test_no_edge_crosses_a_box_and_no_label_covers_one(index):
    drawing = drawings()[index]
    font = FONT[drawing["name"]]
    problems = []
    for transition, edge in zip(sm.TRANSITIONS, drawing["edges"], strict=True):
        ends = {transition.start, transition.goal}
        for box in drawing["boxes"]:
            if box.state_id not in ends and any(
                crosses(p, q, box_rect(drawing, box)) for p, q in segments(edge)
            ):
                problems.append(f"{transition.label} ({transition.id}) crosses {box.label}")
            if edge.label and overlap(label_rect(edge, font), box_rect(drawing, box, 0)):
                problems.append(f"the label {transition.label} ({transition.id}) covers {box.label}")
        for x, y in edge.points:
            assert 0 <= x <= drawing["width"] and 0 <= y <= drawing["height"], transition.label
    labelled = [e for e in drawing["edges"] if e.label]
    for i, edge in enumerate(labelled):
        rect = label_rect(edge, font)
        assert 0 <= rect[0] and rect[2] <= drawing["width"], edge.label
        problems += [f"labels {edge.label} and {other.label} overlap" for other in labelled[i + 1:]
                     if overlap(rect, label_rect(other, font))]
    assert problems == []


def test_the_shutdown_from_unconfigured_goes_round_cleaningup():
    """The case seen on the node page: its label sat under cleaningup and its arrow crossed it."""
    wide = drawings()[0]
    edge = wide["edges"][[t.id for t in sm.TRANSITIONS].index(sm.UNCONFIGURED_SHUTDOWN)]
    cleaningup = next(b for b in wide["boxes"] if b.state_id == sm.CLEANINGUP)
    assert edge.label == "shutdown"
    assert not any(crosses(p, q, box_rect(wide, cleaningup)) for p, q in segments(edge))
    assert not overlap(label_rect(edge, FONT["wide"]), box_rect(wide, cleaningup, 0))


def test_both_drawings_mark_the_current_state_and_the_transitions_open_now():
    for drawing in layout(sm.INACTIVE)["drawings"]:
        assert [b.label for b in drawing["boxes"] if b.current] == ["inactive"]
        assert sorted(e.label for e in drawing["edges"] if e.available) == ["activate", "cleanup", "shutdown"]
    for drawing in layout(sm.INACTIVE, alive=False)["drawings"]:
        assert not any(e.available for e in drawing["edges"])
