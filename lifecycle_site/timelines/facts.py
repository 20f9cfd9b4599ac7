"""The facts a state timeline is made of, as it reads them: audit records (Row), absences
(Absence), and the stretches it cuts the window into (Segment), with the pseudo-states it
draws where no lifecycle state is known (docs/timeline.md). Used by timeline.py."""
from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import NamedTuple

from django.utils.translation import pgettext_lazy

from ros_gateway.shared import state_machine as sm

# Outcomes that count as failures and as restarts. process_lost / process_restarted come from
# crash detection; any other outcome the audit log may learn later is shown, not counted.
FAILURE_OUTCOMES = ("failed", "timed_out", "process_lost")
RESTART_OUTCOMES = ("process_restarted",)
LOST_OUTCOME = "process_lost"

# Pseudo-states: what the timeline shows where no lifecycle state is known.
NOT_SEEN = "not seen yet"
UNKNOWN = "unknown"
GONE = "gone"
UNREACHABLE = "unreachable"
LOST = "process lost"
NOT_READ = "not read"
PSEUDO_STATES = (NOT_SEEN, UNKNOWN, GONE, UNREACHABLE, LOST, NOT_READ)
# How a page names them (the names above are what the API, the drawing's data and the code say).
PSEUDO_STATE_NAMES = {
    NOT_SEEN: pgettext_lazy("timeline state", "not seen yet"), UNKNOWN: pgettext_lazy("timeline state", "unknown"),
    GONE: pgettext_lazy("timeline state", "gone"), UNREACHABLE: pgettext_lazy("timeline state", "unreachable"),
    LOST: pgettext_lazy("timeline state", "process lost"), NOT_READ: pgettext_lazy("timeline state", "not read"),
}


def state_name(state: str) -> str:
    """A timeline's state as a page writes it: a ROS state as it is, a pseudo-state in the active
    language."""
    name = PSEUDO_STATE_NAMES.get(state)
    return state if name is None else str(name)


# duration_ms rather than completed_at: one date less to parse per row (a third of the read time).
# The id comes with any index (it is the row's): the marks link to their record.
ROW_FIELDS = ("requested_at", "duration_ms", "start_state_id", "result_state_id", "outcome", "id")


class Row(NamedTuple):
    """The part of a TransitionRecord a timeline needs (a tuple: thousands are made per page)."""

    requested_at: datetime
    duration_ms: float | None  # None: not completed
    start_state_id: int | None
    result_state_id: int | None
    outcome: str
    id: int | None = None

    @property
    def ended_at(self) -> datetime:
        if not self.duration_ms:
            return self.requested_at
        return self.requested_at + timedelta(milliseconds=self.duration_ms)

    def state_after(self, before: str | None) -> str | None:
        """The state from ``ended_at`` on; ``before`` when the record changed nothing."""
        if self.result_state_id is not None:
            return sm.state_label(self.result_state_id)
        if self.outcome == LOST_OUTCOME:
            return LOST
        if self.outcome in ("failed", "timed_out", *RESTART_OUTCOMES):
            return UNKNOWN  # sent, and the state not read back; or a new process not yet read
        if self.outcome == "rejected" and self.start_state_id is not None:
            return sm.state_label(self.start_state_id)
        return before


class Absence(NamedTuple):
    """A NodeAbsence as the timeline needs it."""

    gone_at: datetime
    back_at: datetime | None  # None: still away
    reason: str

    @property
    def state(self) -> str:
        return {"unreachable": UNREACHABLE, LOST_OUTCOME: LOST}.get(self.reason, GONE)


ABSENCE_FIELDS = ("gone_at", "back_at", "reason")


@dataclass
class Segment:
    state: str
    start: datetime
    end: datetime

    @property
    def seconds(self) -> float:
        return (self.end - self.start).total_seconds()

    def as_dict(self, origin: datetime) -> dict:
        """Its bounds in seconds after ``origin`` (the window's start): thousands of ISO dates
        would cost a page's worth of time."""
        return {"state": self.state, "from_s": round((self.start - origin).total_seconds(), 3),
                "to_s": round((self.end - origin).total_seconds(), 3)}
