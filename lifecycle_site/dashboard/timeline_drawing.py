"""The state timeline drawn as SVG on the server (like graph.py), as wide as the page.

Positions along the time axis are percentages of the drawing's width and heights are pixels,
so the drawing takes the page's width (a 390 px phone or a 1440 px desktop) while its text
keeps its size. It must read in greyscale: each state has its own fill pattern
(templates/dashboard/_timeline_defs.html) and its name written in the bar where it fits, and
each kind of mark its own shape. Times are UTC.
"""
from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from urllib.parse import urlencode

from django.urls import reverse
from django.utils import dateformat
from django.utils.html import escape
from django.utils.safestring import SafeString, mark_safe
from django.utils.translation import gettext as _
from django.utils.translation import ngettext, pgettext

from lifecycle_site.timelines import node as tl
from lifecycle_site.timelines.events import OUTAGE, Event
from lifecycle_site.timelines.facts import state_name
from ros_gateway.shared import state_machine as sm

BAR_H = 26
NAME_H = 18  # a robot's lanes: the node's name above its marks
MARK_H = 18  # the marks above a bar
LANE_GAP = 8
OUTAGE_H = 30  # the gateway's strip at the top, when it had outages in the window
AXIS_H = 40
MIN_SHARE = 1 / 480  # narrower stretches are drawn together as "many changes"
MIN_OUTAGE_SHARE = 1 / 250  # an outage is drawn at least this wide, to be found and tapped
CHAR_W = 6.8  # of the bar labels (12 px), to know whether a name fits in its bar
# A bar's state is written in it where it fits on the narrowest drawing (a 390 px phone), and on
# wide screens (class tl-wide, shown from 900 px) where it fits on one about this wide.
NARROW_PX, WIDE_PX = 340, 1000
BUSY = "many changes"
# Fill pattern (defs id suffix) of each state; transition states share one.
PATTERNS = {
    "active": "active", "inactive": "inactive", "unconfigured": "unconfigured", "finalized": "finalized",
    "errorprocessing": "error", tl.UNKNOWN: "unknown", tl.GONE: "gone", tl.UNREACHABLE: "unreachable",
    tl.LOST: "lost", tl.NOT_SEEN: "notseen", tl.NOT_READ: "notread", BUSY: "busy",
}
DARK = {"active", "finalized"}  # white text on these fills
TRANSITION_PATTERN = "transition"
# Tick steps: the smallest that gives at most MAX_TICKS ticks.
STEPS = [timedelta(minutes=m) for m in (1, 2, 5, 10, 15, 30, 60, 120, 180, 360, 720)] + [
    timedelta(days=d) for d in (1, 2, 7)]
MAX_TICKS = 9


def pattern(state: str) -> str:
    if state in PATTERNS:
        return PATTERNS[state]
    if state in sm.STATE_LABELS.values():
        return TRANSITION_PATTERN
    return PATTERNS[tl.UNKNOWN]


def shown_state(state: str) -> str:
    """A bar's state as the drawing writes it: a ROS state as it is, the others in the active
    language (``state`` stays what the code and data-state say)."""
    return pgettext("timeline state", "many changes") if state == BUSY else state_name(state)


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


def utc(moment: datetime) -> str:
    return moment.astimezone(timezone.utc).strftime("%Y-%m-%d %H:%M:%S")


@dataclass
class Bar:
    x: float  # percent of the width
    w: float
    y: float  # pixels
    state: str
    start: datetime
    end: datetime
    changes: int = 1

    @property
    def title(self) -> str:  # made for the bars drawn only: a busy window has thousands of stretches
        values = {"start": utc(self.start), "end": utc(self.end)}
        if self.state == BUSY:
            # (the same words for one: "1 states" in English, a singular where a language has one)
            return ngettext("%(count)s states from %(start)s to %(end)s UTC, too short to draw apart",
                            "%(count)s states from %(start)s to %(end)s UTC, too short to draw apart",
                            self.changes) % {**values, "count": self.changes}
        length = duration((self.end - self.start).total_seconds())
        return _("%(state)s: %(start)s to %(end)s UTC (%(length)s)") % {
            **values, "state": shown_state(self.state), "length": length}

    @property
    def dark(self) -> bool:
        return self.state in DARK

    def label_class(self) -> str | None:
        """"" when the state's name fits in the bar on a phone, "tl-wide" when only on a wide
        screen, None when it never does."""
        needed = len(shown_state(self.state)) * CHAR_W + 8
        if self.w * NARROW_PX / 100 >= needed:
            return ""
        return "tl-wide" if self.w * WIDE_PX / 100 >= needed else None


def bars(timeline: tl.Timeline, y: float) -> list[Bar]:
    span = timeline.seconds

    def x(moment: datetime) -> float:
        return (moment - timeline.start).total_seconds() / span * 100

    drawn: list[Bar] = []
    for segment in timeline.segments:
        x0, x1 = x(segment.start), x(segment.end)
        last = drawn[-1] if drawn else None
        if x1 - x0 >= MIN_SHARE * 100:
            drawn.append(Bar(x0, x1 - x0, y, segment.state, segment.start, segment.end))
        elif last is not None and last.state == BUSY and x0 - (last.x + last.w) < 0.002:
            last.w, last.end, last.changes = x1 - last.x, segment.end, last.changes + 1
        else:
            drawn.append(Bar(x0, x1 - x0, y, BUSY, segment.start, segment.end))
    return drawn


def bars_svg(drawn: list[Bar], origin: datetime) -> SafeString:
    """The bars' SVG elements, written here rather than in a template loop: a busy hour holds
    hundreds of them, which the template language would take a tenth of a second to render.
    data-s and data-e are a bar's bounds in seconds after ``origin``: a tap shows its details
    (static/js/timeline.js)."""
    parts = []
    for bar in drawn:
        label, text = bar.label_class(), ""
        if label is not None:
            css = f' class="{label}"' if label else ""
            text = (f'<text x="{bar.x + bar.w / 2:.3f}%" y="{bar.y + BAR_H / 2 + 4:.1f}"{css}>'
                    f'{escape(shown_state(bar.state))}</text>')
        parts.append(
            f'<g class="tl-bar{" dark" if bar.dark else ""}" data-state="{escape(bar.state)}" '
            f'data-s="{(bar.start - origin).total_seconds():.0f}" data-e="{(bar.end - origin).total_seconds():.0f}">'
            f"<title>{escape(bar.title)}</title>"
            f'<rect x="{bar.x:.3f}%" y="{bar.y:.1f}" width="{bar.w:.3f}%" height="{BAR_H}" '
            f'fill="url(#tl-{pattern(bar.state)})"/>{text}</g>'
        )
    return mark_safe("".join(parts))  # noqa: S308 - every text in it is escaped above


def _x(moment: datetime, start: datetime, span: float) -> float:
    return min(max((moment - start).total_seconds() / span * 100, 0.0), 100.0)


def marks_svg(events: list[tuple[int, Event]], start: datetime, span: float, y: float) -> SafeString:
    """A mark above the bar for each marked record (``y``: the bar's top), linking to its line
    in the list of events (its id there) and a thin line down through the bar."""
    parts = []
    for index, event in events:
        x = _x(event.at, start, span)
        text = escape(_("%(title)s at %(time)s UTC") % {"title": event.title, "time": utc(event.at)})
        parts.append(
            f'<line class="tl-mark-line" x1="{x:.3f}%" x2="{x:.3f}%" y1="{y - 2:.1f}" y2="{y + BAR_H:.1f}"/>'
            f'<a class="tl-mark tl-mark-{event.kind}" href="#ev-{index}"><title>{text}</title>'
            f'<use href="#tl-m-{event.kind}" x="{x:.3f}%" y="{y:.1f}"/></a>'
        )
    return mark_safe("".join(parts))  # noqa: S308 - escaped above


def outages_svg(outages: list[tuple[int, Event]], start: datetime, end: datetime, y: float) -> SafeString:
    span = (end - start).total_seconds()
    parts = []
    for index, event in outages:
        x0, x1 = _x(event.at, start, span), _x(event.until or end, start, span)
        width = max(x1 - x0, MIN_OUTAGE_SHARE * 100)
        x0 = min(x0, 100 - width)
        values = {"title": event.title, "start": utc(event.at)}
        text = escape(_("%(title)s from %(start)s UTC to %(end)s UTC") % {**values, "end": utc(event.until)}
                      if event.until else _("%(title)s from %(start)s UTC to now") % values)
        # The band, and at its start a mark with room for a finger: a short outage is a sliver.
        parts.append(f'<a class="tl-outage" href="#ev-{index}"><title>{text}</title>'
                     f'<rect x="{x0:.3f}%" y="{y:.1f}" width="{width:.3f}%" height="12" fill="url(#tl-outage)"/>'
                     f'<use href="#tl-m-outage-start" x="{x0:.3f}%" y="{y + 6:.1f}"/></a>')
    return mark_safe("".join(parts))  # noqa: S308 - escaped above


@dataclass
class Tick:
    x: float
    time: str
    date: str
    anchor: str
    minor: bool  # left out on a phone, where every other label would not fit


def tick_step(span: timedelta) -> timedelta:
    return next((step for step in STEPS if span / step <= MAX_TICKS), STEPS[-1])


def ticks(start: datetime, end: datetime) -> list[Tick]:
    step = tick_step(end - start)
    first = datetime(start.year, start.month, start.day, tzinfo=timezone.utc)
    if step >= timedelta(days=7):
        first -= timedelta(days=first.weekday())  # Mondays
    while first < start:
        first += step
    span = (end - start).total_seconds()
    found: list[Tick] = []
    at = first
    while at <= end:
        x = _x(at, start, span)
        anchor = "start" if x < 4 else "end" if x > 96 else "middle"
        # (weekday and month as Django names them in the active language: "Mon", "05 Jan")
        if step >= timedelta(days=1):
            found.append(Tick(x, dateformat.format(at, "D"), dateformat.format(at, "d M"), anchor,
                              len(found) % 2 == 1))
        else:
            new_day = not found or (at.hour == 0 and at.minute == 0)
            found.append(Tick(x, at.strftime("%H:%M"), dateformat.format(at, "d M") if new_day else "", anchor,
                              len(found) % 2 == 1 and not new_day))
        at += step
    return found


def numbered(events: list[Event]) -> list[tuple[int, Event]]:
    """Events oldest first with the number of their line in the list (ids ev-0, ev-1, ...)."""
    return list(enumerate(sorted(events, key=lambda e: e.at)))


def drawing(start: datetime, end: datetime, timelines: list[tl.Timeline], names: bool,
            events: list[tuple[int, Event]]) -> dict:
    span = (end - start).total_seconds()
    outages = [(i, e) for i, e in events if e.kind == OUTAGE]
    y = OUTAGE_H if outages else 0.0
    lanes = []
    for timeline in timelines:
        name_y = y + NAME_H - 5 if names else None
        top = y + (NAME_H if names else 0) + MARK_H
        mine = [(i, e) for i, e in events if e.node is timeline.node]
        node = timeline.node
        lanes.append({
            "timeline": timeline, "name_y": name_y, "top": top,
            "bars": bars_svg(bars(timeline, top), start), "marks": marks_svg(mine, start, span, top),
            "logs": reverse("dashboard:logs", args=["node", node.key]),
            "audit": reverse("dashboard:audit") + "?" + urlencode({"robot": node.robot.name, "node": node.name}),
        })
        y = top + BAR_H + LANE_GAP
    axis_y = y - LANE_GAP + 4
    gateway = outages[0][1].gateway if outages else ""
    return {"height": axis_y + AXIS_H, "bar_h": BAR_H, "lanes": lanes, "axis_y": axis_y, "ticks": ticks(start, end),
            "tick_y": axis_y + 17, "date_y": axis_y + 35, "start_iso": start.isoformat(),
            "outages": outages_svg(outages, start, end, 14) if outages else "", "gateway": gateway}
