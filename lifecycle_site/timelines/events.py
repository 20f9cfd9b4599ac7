"""What a timeline marks besides states: crashes, restarts and failed transitions (audit
records) and the outages of the robot's gateway (ingest/outages.py), each with what an operator
needs to look closer: the node's own reason, its audit record and the log lines of that moment.

Bounded reads: the records come from those the timeline read anyway (their ids included), and
only the newest MAX_EVENTS of them are read again for their reason, by primary key; outages are
one indexed query of at most MAX_OUTAGES.
"""
from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from typing import Iterable
from urllib.parse import quote

from django.urls import reverse
from django.utils.translation import gettext as _
from django.utils.translation import gettext_lazy, pgettext_lazy

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import GatewayOutage, ManagedNode, Robot

# What each marked outcome is called on the page (any other outcome is not marked), in the active
# language when it is read (Event.title).
MARKED = {"failed": pgettext_lazy("timeline mark", "failed transition"),
          "timed_out": pgettext_lazy("timeline mark", "transition timed out"),
          "process_lost": pgettext_lazy("timeline mark", "crash"),
          "process_restarted": pgettext_lazy("timeline mark", "restart")}
# The same with the transition's name.
MARKED_WITH_TRANSITION = {"failed": gettext_lazy("failed transition (%(transition)s)"),
                          "timed_out": gettext_lazy("transition timed out (%(transition)s)")}
OUTAGE = "gateway_outage"
# Why a gateway could take no commands (GatewayOutage.reason), in words.
OUTAGE_REASONS = {"offline": gettext_lazy("no heartbeat: its process ended, froze, or lost Redis"),
                  "stopped": gettext_lazy("it said it stopped"),
                  "quarantined": gettext_lazy("the site cut it off (quarantine)")}
MAX_EVENTS = 50  # a node's timeline; a robot's shares MAX_EVENTS_ROBOT among its nodes
MAX_EVENTS_ROBOT = 100
MAX_OUTAGES = 50
MAX_REASON = 300  # characters of a node's reason shown in the list (the audit record has it whole)


@dataclass
class Event:
    at: datetime
    kind: str  # a key of MARKED, or OUTAGE
    robot: str
    node: ManagedNode | None = None  # None: the gateway's
    record_id: int | None = None
    transition: str = ""
    reason: str = ""
    until: datetime | None = None  # an outage's end; None while it lasts
    gateway: str = ""

    @property
    def title(self) -> str:
        """In the active language."""
        if self.kind == OUTAGE:
            return _("gateway %(gateway)s could take no commands") % {"gateway": self.gateway}
        if self.transition and self.kind in MARKED_WITH_TRANSITION:
            return str(MARKED_WITH_TRANSITION[self.kind]) % {"transition": self.transition}
        return str(MARKED[self.kind])

    def audit_query(self) -> str:
        """The audit page's query narrowed to this moment (an outage: its whole stretch)."""
        query = f"robot={quote(self.robot, safe='')}&since={_second(self.at)}"
        query += f"&until={_second((self.until or self.at) + timedelta(seconds=1))}"
        if self.node is not None:
            query += f"&node={quote(self.node.name, safe='')}&outcome={self.kind}"
        return query

    def logs_target(self) -> tuple[str, str]:
        """The log console that tells about it: the node's, or the robot's for an outage."""
        return ("node", self.node.key) if self.node is not None else ("robot", self.robot)

    @property
    def audit_url(self) -> str:
        return reverse("dashboard:audit") + "?" + self.audit_query()

    @property
    def logs_url(self) -> str:
        """The log console opened at this moment (log_views: ?at=)."""
        return reverse("dashboard:logs", args=list(self.logs_target())) + f"?at={moment_query(self.at)}"

    def as_dict(self) -> dict:
        return {"at": self.at.isoformat(), "kind": self.kind, "title": self.title, "reason": self.reason,
                "node": self.node.key if self.node is not None else None, "record_id": self.record_id,
                "until": self.until.isoformat() if self.until else None}


def _second(moment: datetime) -> str:
    return moment.astimezone(timezone.utc).strftime("%Y-%m-%dT%H:%M:%S")


def moment_query(moment: datetime) -> str:
    """A time as a query string's value needs no quoting: UTC, written with Z."""
    return moment.astimezone(timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def record_events(found: Iterable[tuple[ManagedNode, datetime, str, int | None]], cap: int) -> list[Event]:
    """The newest ``cap`` marked records among ``found`` (node, time, outcome, record id), with
    their transition and the node's reason read by primary key, oldest first."""
    marked = sorted(((n, at, o, i) for n, at, o, i in found if o in MARKED and i is not None),
                    key=lambda e: e[1], reverse=True)[:cap]
    details = {i: (label, error) for i, label, error in TransitionRecord.objects.filter(
        id__in=[e[3] for e in marked]).values_list("id", "transition_label", "error")} if marked else {}
    events = []
    for node, at, outcome, record_id in reversed(marked):
        label, error = details.get(record_id, ("", ""))
        events.append(Event(at, outcome, node.robot.name, node, record_id, label, _short(error)))
    return events


def _short(text: str) -> str:
    return text if len(text) <= MAX_REASON else text[:MAX_REASON - 1] + "…"


def outage_events(robot: Robot, start: datetime, end: datetime) -> list[Event]:
    """The outages of the robot's gateway that overlap the window, oldest first."""
    rows = (GatewayOutage.objects.filter(gateway_id=robot.gateway_id, began__lte=end).exclude(ended__lt=start)
            .order_by("-began").values_list("began", "ended", "reason", "gateway__name")[:MAX_OUTAGES])
    return [Event(began, OUTAGE, robot.name, until=ended, reason=str(OUTAGE_REASONS.get(reason, reason)), gateway=name)
            for began, ended, reason, name in reversed(rows)]
