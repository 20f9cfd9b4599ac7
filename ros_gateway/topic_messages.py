"""What arrives on ~/transition_event and /rosout, turned into facts. No rclpy imports.

A lifecycle node publishes two events per requested transition (``inactive -> activating``,
then ``activating -> active``) and one more when its callback errors
(``activating -> errorprocessing``). TransitionTracker pairs them up into one completed
transition, and tells apart transitions this gateway asked for from those made by
another tool (``ros2 lifecycle``, launch, Nav2, the node itself).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from datetime import datetime, timezone

from ros_gateway.shared import state_machine as sm

LEVEL_NAMES = {10: "DEBUG", 20: "INFO", 30: "WARN", 40: "ERROR", 50: "FATAL"}


@dataclass
class Completed:
    """A transition seen from beginning (or only its end) to a primary state."""

    transition: sm.Transition | None
    start_state: int | None
    result_state: int
    started_at: datetime
    finished_at: datetime
    outcome: str  # succeeded | failed | observed


@dataclass
class TransitionTracker:
    """Per-node pairing of transition events."""

    # Transition id this gateway has requested and not yet seen begin.
    commanded: int | None = None
    # Transition id of our last request whose reply has already set the node's state.
    settled: int | None = None
    # (transition id, end state) of our last request whose beginning and end were both seen: the
    # outcome its answer will tell, should that answer be lost on the way (NodeDriver).
    ended: tuple[int, int] | None = None
    # Transitions of others seen begin (or only end) since then: newer than our request, so a
    # reply handled after them must not put the node's state back (NodeDriver).
    foreign_since_ended: int = 0
    _begun: tuple[sm.Transition, int, datetime, bool] | None = field(default=None, repr=False)

    def observe(self, start_state: int, goal_state: int, transition_id: int) -> tuple[Completed | None, bool]:
        """Feed one event. Returns a Completed transition made by someone else, if one ended,
        and whether the event's goal state is news (False for the late beginning of a request
        of ours whose reply already told the end: the event and the reply travel separately)."""
        now = datetime.now(timezone.utc)
        if sm.is_primary(start_state) and not sm.is_primary(goal_state):
            # rclpy leaves the event's transition field empty (id 0), so the transition is
            # known by its edge: unconfigured -> configuring is "configure", and so on.
            transition = sm.TRANSITIONS_BY_ID.get(transition_id) or sm.transition_between(start_state, goal_state)
            ours = transition is not None and transition.id in (self.commanded, self.settled)
            late = ours and self.settled == transition.id
            if late:  # the beginning of a request whose reply came first; the next may be claimed already
                self.settled = None
            elif ours:
                self.commanded = None
            else:
                self.foreign_since_ended += 1
            self._begun = (transition, start_state, now, ours) if transition else None
            return None, not late
        if not sm.is_primary(goal_state):
            return None, True  # e.g. activating -> errorprocessing: still under way
        begun, self._begun = self._begun, None
        if begun is None:
            # We missed the beginning (subscribed mid-transition): record what we know.
            self.foreign_since_ended += 1
            return Completed(None, None, goal_state, now, now, "observed"), True
        transition, start, started_at, ours = begun
        if ours:
            self.ended, self.foreign_since_ended = (transition.id, goal_state), 0
            return None, True
        outcome = "succeeded" if sm.SUCCESS_GOAL.get(transition.id) == goal_state else "failed"
        return Completed(transition, start, goal_state, started_at, now, outcome), True


    def overtaken(self, transition_id: int) -> bool:
        """Whether another tool's transition began after our request for ``transition_id`` ended
        (both seen in the node's own order): the state that request left is no longer current."""
        return self.ended_as(transition_id) is not None and self.foreign_since_ended > 0

    def ended_as(self, transition_id: int) -> int | None:
        """The state our request for ``transition_id`` ended in, once its events told it."""
        return self.ended[1] if self.ended is not None and self.ended[0] == transition_id else None


def logger_to_node_name(logger: str) -> str:
    """rcl names a node's logger after its namespace and name joined by dots."""
    return "/" + logger.replace(".", "/")


def owning_node(logger: str, node_names: set[str]) -> str | None:
    """The managed node a logger belongs to: itself, or the nearest parent (child loggers)."""
    candidate = logger_to_node_name(logger)
    while candidate:
        if candidate in node_names:
            return candidate
        candidate = candidate.rsplit("/", 1)[0]
    return None


@dataclass
class LogEntry:
    """One /rosout record as plain data, copied off the ROS message on arrival."""

    domain_id: int
    stamp: datetime
    level: int
    logger: str
    message: str
    file: str
    function: str
    line: int

    @classmethod
    def from_msg(cls, domain_id: int, msg) -> "LogEntry":
        stamp = datetime.fromtimestamp(msg.stamp.sec + msg.stamp.nanosec / 1e9, timezone.utc)
        return cls(domain_id, stamp, int(msg.level), msg.name, msg.msg, msg.file, msg.function, int(msg.line))


class LogBuffer:
    """Bounded hand-over from the executor threads to the writer: never grows past ``limit``.

    When full, the oldest records are dropped and counted, so a flooding node costs a fixed
    amount of memory and the newest records, the ones an operator needs, survive.
    """

    def __init__(self, limit: int) -> None:
        self._records: deque[LogEntry] = deque(maxlen=limit)
        self.dropped = 0
        self.received = 0

    def append(self, entry: LogEntry) -> None:
        # deque append/popleft are atomic under the GIL: safe across threads without a lock.
        if len(self._records) == self._records.maxlen:
            self.dropped += 1
        self._records.append(entry)
        self.received += 1

    def drain(self, max_items: int) -> list[LogEntry]:
        batch = []
        while self._records and len(batch) < max_items:
            batch.append(self._records.popleft())
        return batch

    def __len__(self) -> int:
        return len(self._records)

