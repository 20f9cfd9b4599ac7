"""State timeline pages of a node and of a robot, drawn as SVG on the server (like graph.py).

The drawing must read in greyscale: each state has its own fill pattern (see
templates/dashboard/_timeline_defs.html) and its name written in the bar where it fits, plus
the legend table. Times are UTC. The drawing is 480 units wide and scales down to a phone.
"""
from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta, timezone

from django.http import Http404, HttpRequest, HttpResponse
from django.shortcuts import render
from django.utils.html import escape
from django.utils.safestring import SafeString, mark_safe

from lifecycle_site.dashboard import timeline as tl
from lifecycle_site.dashboard.access import viewer_required
from lifecycle_site.dashboard.robot_timeline import robot_timeline as robot_timeline_of
from lifecycle_site.dashboard.views import node_or_404
from lifecycle_site.fleet.models import Robot
from ros_gateway.shared import state_machine as sm

WIDTH = 480
BAR_H = 26
NAME_H = 19  # a robot's lanes: the node's name above its bar
LANE_GAP = 8
AXIS_H = 40
MIN_BAR = 1.0  # narrower stretches are drawn together as "many changes"
CHAR_W = 6.4  # of the bar labels (12 px), to know whether a name fits in its bar
BUSY = "many changes"
TICKS = {"hour": timedelta(minutes=15), "day": timedelta(hours=3), "week": timedelta(days=1)}
# Fill pattern (defs id suffix) of each state; transition states share one.
PATTERNS = {
    "active": "active", "inactive": "inactive", "unconfigured": "unconfigured", "finalized": "finalized",
    "errorprocessing": "error", tl.UNKNOWN: "unknown", tl.GONE: "gone", tl.UNREACHABLE: "unreachable",
    tl.LOST: "lost", tl.NOT_SEEN: "notseen", tl.NOT_READ: "notread", BUSY: "busy",
}
DARK = {"active", "finalized"}  # white text on these fills
TRANSITION_PATTERN = "transition"


def pattern(state: str) -> str:
    if state in PATTERNS:
        return PATTERNS[state]
    if state in sm.STATE_LABELS.values():
        return TRANSITION_PATTERN
    return PATTERNS[tl.UNKNOWN]


@dataclass
class Bar:
    x: float
    w: float
    y: float
    state: str
    start: datetime
    end: datetime
    changes: int = 1

    @property
    def title(self) -> str:  # made for the bars drawn only: a busy window has thousands of stretches
        if self.state == BUSY:
            return f"{self.changes} states from {_utc(self.start)} to {_utc(self.end)} UTC, too short to draw apart"
        return (f"{self.state}: {_utc(self.start)} to {_utc(self.end)} UTC "
                f"({duration((self.end - self.start).total_seconds())})")

    @property
    def pattern(self) -> str:
        return pattern(self.state)

    @property
    def dark(self) -> bool:
        return self.state in DARK

    @property
    def label(self) -> str:
        """The state's name, when it fits in the bar."""
        return self.state if self.w >= len(self.state) * CHAR_W + 8 else ""

    @property
    def label_x(self) -> float:
        return self.x + self.w / 2


@dataclass
class Tick:
    x: float
    time: str
    date: str
    anchor: str


def duration(seconds: float) -> str:
    """12 s, 4 min 05 s, 3 h 20 min, 2 d 4 h."""
    seconds = round(seconds)
    if seconds < 60:
        return f"{seconds} s"
    minutes, secs = divmod(seconds, 60)
    if minutes < 60:
        return f"{minutes} min {secs:02d} s"
    hours, minutes = divmod(minutes, 60)
    if hours < 24:
        return f"{hours} h {minutes:02d} min"
    days, hours = divmod(hours, 24)
    return f"{days} d {hours} h"


def _utc(moment: datetime) -> str:
    return moment.astimezone(timezone.utc).strftime("%Y-%m-%d %H:%M:%S")


def bars(timeline: tl.Timeline, y: float) -> list[Bar]:
    span = timeline.seconds

    def x(moment: datetime) -> float:
        return (moment - timeline.start).total_seconds() / span * WIDTH

    drawn: list[Bar] = []
    for segment in timeline.segments:
        x0, x1 = x(segment.start), x(segment.end)
        last = drawn[-1] if drawn else None
        if x1 - x0 >= MIN_BAR:
            drawn.append(Bar(x0, x1 - x0, y, segment.state, segment.start, segment.end))
        elif last is not None and last.state == BUSY and x0 - (last.x + last.w) < 0.01:
            last.w, last.end, last.changes = x1 - last.x, segment.end, last.changes + 1
        else:
            drawn.append(Bar(x0, x1 - x0, y, BUSY, segment.start, segment.end))
    return drawn


def bars_svg(drawn: list[Bar]) -> SafeString:
    """The bars' SVG elements, written here rather than in a template loop: a busy hour holds
    hundreds of them, which the template language would take a tenth of a second to render."""
    parts = []
    for bar in drawn:
        label = bar.label
        text = (f'<text x="{bar.label_x:.1f}" y="{bar.y + BAR_H / 2 + 4:.1f}">{escape(label)}</text>'
                if label else "")
        parts.append(
            f'<g class="tl-bar{" dark" if bar.dark else ""}" data-state="{escape(bar.state)}">'
            f"<title>{escape(bar.title)}</title>"
            f'<rect x="{bar.x:.2f}" y="{bar.y:.1f}" width="{bar.w:.2f}" height="{BAR_H}" '
            f'fill="url(#tl-{bar.pattern})"/>{text}</g>'
        )
    return mark_safe("".join(parts))  # noqa: S308 - every text in it is escaped above


def ticks(window: str, start: datetime, end: datetime) -> list[Tick]:
    step = TICKS[window]
    first = datetime(start.year, start.month, start.day, tzinfo=timezone.utc)
    while first < start:
        first += step
    found, at = [], first
    while at <= end:
        x = (at - start).total_seconds() / (end - start).total_seconds() * WIDTH
        anchor = "start" if x < 20 else "end" if x > WIDTH - 20 else "middle"
        if window == "week":
            found.append(Tick(x, at.strftime("%a"), at.strftime("%d %b"), anchor))
        else:
            new_day = not found or (at.hour == 0 and at.minute == 0)
            found.append(Tick(x, at.strftime("%H:%M"), at.strftime("%d %b") if new_day else "", anchor))
        at += step
    return found


def drawing(window: str, start: datetime, end: datetime, timelines: list[tl.Timeline], names: bool) -> dict:
    lanes, y = [], 0.0
    for timeline in timelines:
        name_y = y + NAME_H - 4 if names else None
        top = y + (NAME_H if names else 0)
        lanes.append({"timeline": timeline, "name_y": name_y, "top": top, "bars": bars_svg(bars(timeline, top))})
        y = top + BAR_H + LANE_GAP
    axis_y = y - LANE_GAP + 4
    return {"width": WIDTH, "height": axis_y + AXIS_H, "bar_h": BAR_H,
            "lanes": lanes, "axis_y": axis_y, "ticks": ticks(window, start, end), "tick_y": axis_y + 17,
            "date_y": axis_y + 35}


def legend(timeline_list: list[tl.Timeline]) -> list[dict]:
    """Time in each state, over all the given timelines (a robot: summed over its nodes)."""
    totals: dict[str, float] = {}
    for timeline in timeline_list:
        for state, seconds in timeline.time_in_state.items():
            totals[state] = totals.get(state, 0.0) + seconds
    whole = sum(t.seconds for t in timeline_list) or 1.0
    return [{"state": s, "pattern": pattern(s), "time": duration(v), "percent": 100 * v / whole}
            for s, v in sorted(totals.items(), key=lambda kv: -kv[1])]


def _window(request: HttpRequest) -> tuple[str, str]:
    asked = request.GET.get("window", tl.DEFAULT_WINDOW)
    if asked in tl.WINDOWS:
        return asked, ""
    return tl.DEFAULT_WINDOW, f"There is no window {asked[:40]!r}: showing the last {tl.DEFAULT_WINDOW}."


def _summary(timeline: tl.Timeline) -> dict:
    availability, of_known = timeline.availability, timeline.availability_of_known
    return {
        "timeline": timeline,
        "node": timeline.node,
        "availability": None if availability is None else 100 * availability,
        "of_known": None if of_known is None or not timeline.unknown_seconds else 100 * of_known,
        "unknown": 100 * timeline.unknown_seconds / timeline.seconds,
    }


def _context(window: str, warning: str, start: datetime, end: datetime) -> dict:
    return {"window": window, "windows": list(tl.WINDOWS), "warning": warning,
            "start": _utc(start), "end": _utc(end), "unknown_states": tl.PSEUDO_STATES}


@viewer_required
def node_timeline(request: HttpRequest, key: str) -> HttpResponse:
    node = node_or_404(key)
    window, warning = _window(request)
    timeline = tl.node_timeline(node, window)
    return render(request, "dashboard/timeline_node.html", {
        **_context(window, warning, timeline.start, timeline.end),
        "summary": _summary(timeline),
        "timeline": timeline,
        "node": node,
        "outcomes": sorted(timeline.outcomes.items()),
        "drawing": drawing(window, timeline.start, timeline.end, [timeline], names=False),
        "legend": legend([timeline]),
    })


@viewer_required
def robot_timeline(request: HttpRequest, robot: str) -> HttpResponse:
    found = Robot.objects.filter(name=robot).first()
    if found is None:
        raise Http404(f"There is no robot {robot}.")
    window, warning = _window(request)
    timelines = robot_timeline_of(found, window)
    availability = timelines.availability
    return render(request, "dashboard/timeline_robot.html", {
        **_context(window, warning, timelines.start, timelines.end),
        "robot": found,
        "timelines": timelines,
        "availability": None if availability is None else 100 * availability,
        "cut_before": _utc(timelines.cut_before) if timelines.cut_before else "",
        "rows": [_summary(t) for t in timelines.nodes],
        "drawing": drawing(window, timelines.start, timelines.end, timelines.nodes, names=True),
        "legend": legend(timelines.nodes),
    })
