"""A node's states over a window, rebuilt from the audit log (a robot's nodes together: robot.py).

What the records tell, and what they cannot:
- every transition attempt and every change made by another tool ("observed") is a
  TransitionRecord: its ``from`` state held just before ``requested_at``, its ``to`` state from
  ``completed_at`` on;
- ManagedNode.state_changed is when the node's last state fact arrived: from then on it was in
  ManagedNode.state_label (state facts are sent on change only);
- a node's absences (node.gone to its return) are NodeAbsence records; a node away since before
  they were kept is away since ManagedNode.last_seen;
- where two neighbouring facts disagree (a record ends in ``active``, the next starts from
  ``unconfigured``: its process was restarted, or an event was lost), when the change happened
  is not known: that stretch is drawn as "unknown" instead of guessed.

Reads are bounded: one indexed query for the state before the window, at most MAX_ROWS
records and MAX_ABSENCES absences of the window (newest first; what is older is drawn as "not
read"), one count per outcome, and for the marks (events.py) the reasons of at most
MAX_EVENTS marked records by primary key and the gateway's outages in one indexed query.
Availability counts from when the node was first seen ("not seen yet" is neither).
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from datetime import datetime
from functools import cached_property
from typing import Iterable

from django.db.models import Count
from django.utils.formats import number_format
from django.utils.translation import gettext

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import ManagedNode, NodeAbsence
from lifecycle_site.timelines.events import MAX_EVENTS, Event, outage_events, record_events
from lifecycle_site.timelines.facts import (  # noqa: F401 (names of this module too)
    ABSENCE_FIELDS,
    FAILURE_OUTCOMES,
    GONE,
    LOST,
    LOST_OUTCOME,
    NOT_READ,
    NOT_SEEN,
    PSEUDO_STATES,
    RESTART_OUTCOMES,
    ROW_FIELDS,
    UNKNOWN,
    UNREACHABLE,
    Absence,
    Row,
    Segment,
    state_name,
)
from lifecycle_site.timelines.windows import DEFAULT_WINDOW, WINDOWS, Window, window_of  # noqa: F401
from ros_gateway.shared import state_machine as sm

# Records read per timeline at most (a node's page; a robot's page shares them among its nodes).
MAX_ROWS = 3000
MAX_ROWS_ROBOT = 5000
MAX_ABSENCES = 1000
MAX_ABSENCES_ROBOT = 2000

# The facts' shapes and the pseudo-states are in facts.py (imported above: they are
# part of this module's names too).


@dataclass
class Timeline:
    """One node over one window."""

    node: ManagedNode
    window: str
    start: datetime
    end: datetime
    segments: list[Segment]
    outcomes: dict[str, int]  # records of the window by outcome (a robot's timeline: failures and restarts only)
    rows_read: int
    cut_before: datetime | None  # records older than this were not read
    notes: list[str] = field(default_factory=list)
    absences: int = 0  # times the node went away within the window
    events: list[Event] = field(default_factory=list)  # its marked records (events.py)
    outages: list[Event] = field(default_factory=list)  # its gateway's, in the window

    @property
    def seconds(self) -> float:
        return (self.end - self.start).total_seconds()

    @cached_property
    def time_in_state(self) -> dict[str, float]:
        totals: Counter[str] = Counter()
        for segment in self.segments:
            totals[segment.state] += segment.seconds
        return dict(totals)

    @property
    def desired(self) -> str:
        return self.node.desired_state

    @property
    def observed_seconds(self) -> float:
        """The window's time since the node was first seen: before, it did not exist for the site."""
        return self.seconds - self.time_in_state.get(NOT_SEEN, 0.0)

    @property
    def counted_from(self) -> datetime | None:
        """When the node was first seen, if that was inside the window ("not seen yet" comes first)."""
        first = self.segments[0] if self.segments else None
        return first.end if first is not None and first.state == NOT_SEEN else None

    @property
    def availability(self) -> float | None:
        """Share of the window since the node was first seen spent in the desired state, 0-1;
        None without a desired state, or for a node not seen in the window."""
        if not self.desired or self.observed_seconds <= 0:
            return None
        return self.time_in_state.get(self.desired, 0.0) / self.observed_seconds

    @property
    def availability_of_known(self) -> float | None:
        """The same share of the time whose state is known (not "unknown" nor "not read")."""
        known = self.observed_seconds - self.unknown_seconds
        if not self.desired or known <= 0:
            return None
        return self.time_in_state.get(self.desired, 0.0) / known

    @property
    def unknown_seconds(self) -> float:
        spent = self.time_in_state
        return sum(spent.get(s, 0.0) for s in (UNKNOWN, NOT_READ))

    @property
    def failures(self) -> int:
        return sum(self.outcomes.get(o, 0) for o in FAILURE_OUTCOMES)

    @property
    def restarts(self) -> int:
        return sum(self.outcomes.get(o, 0) for o in RESTART_OUTCOMES)

    def as_dict(self) -> dict:
        availability = self.availability
        return {
            "node": self.node.key,
            "robot": self.node.robot.name,
            "name": self.node.name,
            "window": {"name": self.window, "start": self.start.isoformat(), "end": self.end.isoformat()},
            "desired_state": self.desired or None,
            "availability_percent": None if availability is None else round(100 * availability, 3),
            "counted_from": self.counted_from.isoformat() if self.counted_from else None,
            "availability_of_known_percent": _percent(self.availability_of_known),
            "unknown_percent": round(100 * self.unknown_seconds / self.seconds, 3),
            "time_in_state": [{"state": s, "seconds": round(v, 3), "percent": round(100 * v / self.seconds, 3)}
                              for s, v in sorted(self.time_in_state.items(), key=lambda kv: -kv[1])],
            "failures": self.failures,
            "restarts": self.restarts,
            "absences": self.absences,
            "outcomes": self.outcomes,
            "records_read": self.rows_read,
            "not_read_before": self.cut_before.isoformat() if self.cut_before else None,
            "notes": self.notes,
            "segments": [s.as_dict(self.start) for s in self.segments],
            "events": [e.as_dict() for e in (*self.outages, *self.events)],
        }


def _percent(share: float | None) -> float | None:
    return None if share is None else round(100 * share, 3)


def as_window(window: str | Window, now: datetime | None = None) -> Window:
    return window if isinstance(window, Window) else window_of(window, now)


class _Builder:
    """Walks a node's facts in time order and cuts the window into segments."""

    def __init__(self, start: datetime, end: datetime, state: str) -> None:
        self.end = end
        self.at = start
        self.state = state
        # True from the node's discovery (its state read, not recorded) to its next fact: the
        # next record's "from" state is the one it was found in (any change between would be
        # on record, as "observed").
        self.discovered = False
        self.segments: list[Segment] = []

    def close(self, until: datetime, state: str | None = None) -> None:
        """The current state lasted until ``until`` (``state`` instead, if given)."""
        until = min(until, self.end)
        if until <= self.at:
            return
        label = state or self.state
        if self.segments and self.segments[-1].state == label:
            self.segments[-1].end = until
        else:
            self.segments.append(Segment(label, self.at, until))
        self.at = until

    def held(self, at: datetime, state: str) -> None:
        """The node was in ``state`` just before ``at``: if that is not what we had, the change
        to it happened at an unknown time since the last fact."""
        if self.discovered:
            self.state, self.discovered = state, False
        if state != self.state and self.state not in (NOT_READ, NOT_SEEN) and not _enters(self.state, state):
            self.close(at, UNKNOWN)
            self.state = state
        else:
            self.close(at)
            self.state = state

    def became(self, at: datetime, state: str | None) -> None:
        self.close(at)
        self.discovered = False
        if state is not None:
            self.state = state


def _enters(state: str, transition_state: str) -> bool:
    """Whether ``transition_state`` is where a transition from primary ``state`` goes first
    (a node seen "activating" was "inactive" until then)."""
    return any(sm.state_label(t.start) == state and sm.state_label(t.goal) == transition_state
               for t in sm.TRANSITIONS)


def build(node: ManagedNode, window: str, start: datetime, end: datetime, before: Row | None,
          rows: list[Row], cut_before: datetime | None, outcomes: dict[str, int],
          absences: Iterable[Absence] = ()) -> Timeline:
    """The timeline of ``node`` from its facts: ``before`` (the last record before ``start``),
    ``rows`` (the records of the window that were read, any order), ``absences`` (those that
    overlap the window) and the node's own row."""
    rows, read = sorted(rows, key=lambda r: r.requested_at), len(rows)
    if cut_before is not None:  # the absences may have been cut later than the records
        rows = [r for r in rows if r.requested_at >= cut_before]
        absences = [a for a in absences if a.gone_at >= cut_before]
    initial, known_at = None, None
    if before is not None and before.ended_at > start:  # under way when the window began
        rows.insert(0, before)
        if before.start_state_id is not None:
            initial, known_at = sm.state_label(before.start_state_id), before.requested_at
    elif before is not None:
        initial, known_at = before.state_after(UNKNOWN), before.ended_at
    changed, first_seen = node.state_changed, node.first_seen
    if changed is not None and changed <= start and (known_at is None or changed >= known_at):
        initial = node.state_label  # its last state fact is older than the window: still so
    if cut_before is not None:
        initial = NOT_READ
    elif initial is None and (first_seen is None or first_seen > start):
        initial = NOT_SEEN
    builder = _Builder(start, end, initial or UNKNOWN)
    if initial == NOT_SEEN and first_seen is not None:
        builder.became(first_seen, UNKNOWN)
        builder.discovered = True
    away_now = False
    for _, kind, event in _events(rows, absences, start, end):
        if kind == _GONE:
            builder.became(max(event.gone_at, start), event.state)
            away_now = event.back_at is None
        elif kind == _BACK:
            builder.became(event.back_at, UNKNOWN)
            builder.discovered = True  # found again: its state was read then, not recorded
        else:
            if event.outcome in RESTART_OUTCOMES:
                builder.became(max(event.requested_at, start), None)  # a new process: no "from" to check
            elif event.start_state_id is not None:
                builder.held(max(event.requested_at, start), sm.state_label(event.start_state_id))
            builder.became(max(event.ended_at, start), event.state_after(builder.state))
    if changed is not None and start < changed <= end and changed >= builder.at and not away_now:
        builder.held(changed, node.state_label)  # the node's last state fact
    notes: list[str] = []  # (in the active language: made for the page or the API answer that asks)
    if away_now and node.last_seen:
        notes.append(_not_seen(node))
    elif not node.alive and first_seen is not None:  # away since before absences were recorded
        builder.close(max(node.last_seen or start, start))
        builder.state = UNREACHABLE if node.gone_reason == "unreachable" else GONE
        if node.last_seen:
            notes.append(_not_seen(node))
    builder.close(end)
    if cut_before is not None:
        notes.append(gettext("Only the newest %(count)s records of the window were read; before %(time)s UTC the "
                             "timeline shows \"%(not_read)s\". The counts of failures and restarts cover the whole "
                             "window.") % {"count": number_format(read, force_grouping=True),
                                           "time": f"{cut_before:%Y-%m-%d %H:%M:%S}",
                                           "not_read": state_name(NOT_READ)})
    went = sum(1 for a in absences if a.gone_at >= start)
    return Timeline(node, window, start, end, builder.segments, outcomes, read, cut_before, notes, went)


def _not_seen(node: ManagedNode) -> str:
    values = {"time": f"{node.last_seen:%Y-%m-%d %H:%M:%S}"}
    if node.gone_reason == "unreachable":
        return gettext("Not seen since %(time)s UTC (its process stopped answering).") % values
    return gettext("Not seen since %(time)s UTC.") % values


_ROW, _GONE, _BACK = 0, 1, 2  # at equal times: a process_lost record before the node.gone it comes with


def _events(rows: list[Row], absences: Iterable[Absence], start: datetime, end: datetime):
    """Records and absence bounds in time order, as (time, kind, record or absence)."""
    events: list[tuple[datetime, int, Row | Absence]] = [(r.requested_at, _ROW, r) for r in rows]
    for absence in absences:
        events.append((absence.gone_at, _GONE, absence))
        if absence.back_at is not None and absence.back_at <= end:
            events.append((max(absence.back_at, start), _BACK, absence))
    events.sort(key=lambda e: (e[0], e[1]))
    return events


def _rows(values: Iterable[tuple]) -> list[Row]:
    return [Row(*v) for v in values]


def read_newest(values, fields: tuple[str, ...], cap: int) -> tuple[list[tuple], datetime | None]:
    """At most ``cap`` rows of ``values`` (a values_list ending in ``fields``, whose first is
    the time), newest first; and the time before which older ones were left out."""
    found = list(values.order_by(f"-{fields[0]}")[: cap + 1])
    if len(found) <= cap:
        return found, None
    found = found[:cap]
    return found, found[-1][-len(fields)]  # the time of the oldest one read


def overlapping(absences, start: datetime, end: datetime):
    return absences.filter(gone_at__lte=end).exclude(back_at__lt=start)


def later(a: datetime | None, b: datetime | None) -> datetime | None:
    return max(a, b) if a is not None and b is not None else a or b


def node_timeline(node: ManagedNode, window: str | Window = DEFAULT_WINDOW, now: datetime | None = None,
                  cap: int = MAX_ROWS, absence_cap: int = MAX_ABSENCES) -> Timeline:
    window = as_window(window, now)
    start, end = window.start, window.end
    records = TransitionRecord.objects.filter(node=node)
    inside = records.filter(requested_at__gte=start, requested_at__lte=end)
    values, cut_before = read_newest(inside.values_list(*ROW_FIELDS), ROW_FIELDS, cap)
    away, absences_cut = read_newest(
        overlapping(NodeAbsence.objects.filter(node=node), start, end).values_list(*ABSENCE_FIELDS), ABSENCE_FIELDS,
        absence_cap)
    cut_before = later(cut_before, absences_cut)
    before = None
    if cut_before is None:
        found = records.filter(requested_at__lt=start).order_by("-requested_at").values_list(*ROW_FIELDS).first()
        before = Row(*found) if found else None
    outcomes = dict(inside.order_by().values_list("outcome").annotate(n=Count("id")))
    rows = _rows(values)
    timeline = build(node, window.name, start, end, before, rows, cut_before, outcomes, [Absence(*a) for a in away])
    timeline.events = record_events(((node, r.requested_at, r.outcome, r.id) for r in rows), MAX_EVENTS)
    # Its gateway's outages while the node was there to be hidden by them, as availability counts.
    timeline.outages = outage_events(node.robot, max(start, node.first_seen or start), end)
    return timeline
