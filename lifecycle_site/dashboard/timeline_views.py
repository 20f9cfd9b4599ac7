"""State timeline pages of a node and of a robot: the drawing (timeline_drawing.py), the figures,
the time in each state and the events of the window (crashes, restarts, failed transitions,
gateway outages), each linking to its audit record and to the log lines of that moment."""
from __future__ import annotations

from datetime import datetime, timezone

from django.http import Http404, HttpRequest, HttpResponse
from django.shortcuts import render
from django.urls import reverse
from django.utils.translation import gettext as _

from lifecycle_site.dashboard.access import viewer_required
from lifecycle_site.dashboard.timeline_drawing import drawing, duration, numbered, pattern, utc
from lifecycle_site.dashboard.views import node_or_404
from lifecycle_site.diagnostics import history as diagnostic_history
from lifecycle_site.fleet.models import Robot
from lifecycle_site.timelines import node as tl
from lifecycle_site.timelines import windows as tw
from lifecycle_site.timelines.events import MAX_EVENTS, MAX_EVENTS_ROBOT, OUTAGE, moment_query
from lifecycle_site.timelines.robot import robot_timeline as robot_timeline_of


def legend(timeline_list: list[tl.Timeline]) -> list[dict]:
    """Time in each state, over all the given timelines (a robot: summed over its nodes)."""
    totals: dict[str, float] = {}
    for timeline in timeline_list:
        for state, seconds in timeline.time_in_state.items():
            totals[state] = totals.get(state, 0.0) + seconds
    whole = sum(t.seconds for t in timeline_list) or 1.0
    return [{"state": s, "pattern": pattern(s), "time": duration(v), "percent": 100 * v / whole}
            for s, v in sorted(totals.items(), key=lambda kv: -kv[1])]


def _summary(timeline: tl.Timeline) -> dict:
    availability, of_known = timeline.availability, timeline.availability_of_known
    counted_from = timeline.counted_from
    return {
        "timeline": timeline,
        "node": timeline.node,
        "availability": None if availability is None else 100 * availability,
        "of_known": None if of_known is None or not timeline.unknown_seconds else 100 * of_known,
        "unknown": 100 * timeline.unknown_seconds / timeline.seconds,
        # Availability counts from when the node was first seen, if that was inside the window.
        "counted_from": utc(counted_from) if counted_from else "",
        "observed": duration(timeline.observed_seconds),
        "never_seen": timeline.observed_seconds <= 0,
    }


def _events(numbered_events: list) -> list[dict]:
    """The list's lines, every text and link made here: a week can hold a hundred of them, and
    the URLs are reversed once per node rather than once per line."""
    audit = reverse("dashboard:audit")
    bases: dict[tuple[str, str], str] = {}
    rows = []
    for index, event in numbered_events:
        target = event.logs_target()
        if target not in bases:
            bases[target] = reverse("dashboard:logs", args=list(target))
        row = {"id": f"ev-{index}", "kind": event.kind, "at": utc(event.at), "until": "", "title": event.title,
               "reason": event.reason, "audit_url": f"{audit}?{event.audit_query()}",
               "logs_url": f"{bases[target]}?at={moment_query(event.at)}", "node": event.node}
        if event.kind == OUTAGE:
            row["until"] = (f"{utc(event.until)} UTC ({duration((event.until - event.at).total_seconds())})"
                            if event.until else _("still now"))
        rows.append(row)
    return rows


def _field(moment: datetime) -> str:
    """As a datetime-local field takes it, in UTC."""
    return moment.astimezone(timezone.utc).strftime("%Y-%m-%dT%H:%M")


def window_context(window: tw.Window, warning: str) -> dict:
    return {"window": window, "windows": [(name, tw.LABELS[name]) for name in tw.WINDOWS], "warning": warning,
            "custom": window.name == tw.CUSTOM, "start": utc(window.start), "end": utc(window.end),
            "from_value": _field(window.start), "to_value": _field(window.end),
            "unknown_states": tl.PSEUDO_STATES}


@viewer_required
def node_timeline(request: HttpRequest, key: str) -> HttpResponse:
    node = node_or_404(key)
    window, warning = tw.page_window(request.GET)
    timeline = tl.node_timeline(node, window)
    events = numbered([*timeline.outages, *timeline.events])
    return render(request, "dashboard/timeline_node.html", {
        **window_context(window, warning),
        "summary": _summary(timeline),
        "timeline": timeline,
        "node": node,
        "outcomes": sorted(timeline.outcomes.items()),
        "drawing": drawing(window.start, window.end, [timeline], False, events),
        "events": _events(events),
        "events_capped": MAX_EVENTS if len(timeline.events) >= MAX_EVENTS else 0,
        "legend": legend([timeline]),
        "diagnostics": diagnostic_history.node_lanes(node.robot, node.name, window.start, window.end),
    })


@viewer_required
def robot_timeline(request: HttpRequest, robot: str) -> HttpResponse:
    found = Robot.objects.filter(name=robot).first()
    if found is None:
        raise Http404(_("There is no robot %(robot)s.") % {"robot": robot})
    window, warning = tw.page_window(request.GET)
    timelines = robot_timeline_of(found, window)
    availability = timelines.availability
    events = numbered([*timelines.outages, *timelines.events])
    return render(request, "dashboard/timeline_robot.html", {
        **window_context(window, warning),
        "robot": found,
        "timelines": timelines,
        "availability": None if availability is None else 100 * availability,
        "cut_before": utc(timelines.cut_before) if timelines.cut_before else "",
        "rows": [_summary(t) for t in timelines.nodes],
        "drawing": drawing(window.start, window.end, timelines.nodes, True, events),
        "events": _events(events),
        "events_capped": MAX_EVENTS_ROBOT if len(timelines.events) >= MAX_EVENTS_ROBOT else 0,
        "legend": legend(timelines.nodes),
    })
