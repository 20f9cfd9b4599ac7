"""Facts of the ROS 2 managed-node (lifecycle) state machine.

Pure data, no rclpy: the web side and the gateway both import it. Ids and labels are
the ones of lifecycle_msgs/msg/State and lifecycle_msgs/msg/Transition (design article
"Managed nodes", thesis section 2.5).
"""
from __future__ import annotations

from dataclasses import dataclass

# Primary states
UNKNOWN = 0
UNCONFIGURED = 1
INACTIVE = 2
ACTIVE = 3
FINALIZED = 4
# Transition states
CONFIGURING = 10
CLEANINGUP = 11
SHUTTINGDOWN = 12
ACTIVATING = 13
DEACTIVATING = 14
ERRORPROCESSING = 15

STATE_LABELS: dict[int, str] = {
    UNKNOWN: "unknown",
    UNCONFIGURED: "unconfigured",
    INACTIVE: "inactive",
    ACTIVE: "active",
    FINALIZED: "finalized",
    CONFIGURING: "configuring",
    CLEANINGUP: "cleaningup",
    SHUTTINGDOWN: "shuttingdown",
    ACTIVATING: "activating",
    DEACTIVATING: "deactivating",
    ERRORPROCESSING: "errorprocessing",
}
PRIMARY_STATES = (UNCONFIGURED, INACTIVE, ACTIVE, FINALIZED)
# The states a node may be kept in (its desired state: recovery drives it back there).
DESIRED_STATES = {"unconfigured": UNCONFIGURED, "inactive": INACTIVE, "active": ACTIVE}


@dataclass(frozen=True)
class Transition:
    """One edge of the state machine."""

    id: int
    label: str
    start: int
    goal: int
    # True for transitions a client may request through ~/change_state.
    external: bool = True

    def as_dict(self) -> dict:
        return {"id": self.id, "label": self.label}


# External transitions: what an operator may request.
CONFIGURE = 1
CLEANUP = 2
ACTIVATE = 3
DEACTIVATE = 4
UNCONFIGURED_SHUTDOWN = 5
INACTIVE_SHUTDOWN = 6
ACTIVE_SHUTDOWN = 7

TRANSITIONS: tuple[Transition, ...] = (
    Transition(CONFIGURE, "configure", UNCONFIGURED, CONFIGURING),
    Transition(CLEANUP, "cleanup", INACTIVE, CLEANINGUP),
    Transition(ACTIVATE, "activate", INACTIVE, ACTIVATING),
    Transition(DEACTIVATE, "deactivate", ACTIVE, DEACTIVATING),
    Transition(UNCONFIGURED_SHUTDOWN, "shutdown", UNCONFIGURED, SHUTTINGDOWN),
    Transition(INACTIVE_SHUTDOWN, "shutdown", INACTIVE, SHUTTINGDOWN),
    Transition(ACTIVE_SHUTDOWN, "shutdown", ACTIVE, SHUTTINGDOWN),
    # Internal transitions, driven by the result of the node's own callbacks.
    Transition(10, "on_configure_success", CONFIGURING, INACTIVE, False),
    Transition(11, "on_configure_failure", CONFIGURING, UNCONFIGURED, False),
    Transition(12, "on_configure_error", CONFIGURING, ERRORPROCESSING, False),
    Transition(20, "on_cleanup_success", CLEANINGUP, UNCONFIGURED, False),
    Transition(21, "on_cleanup_failure", CLEANINGUP, INACTIVE, False),
    Transition(22, "on_cleanup_error", CLEANINGUP, ERRORPROCESSING, False),
    Transition(30, "on_activate_success", ACTIVATING, ACTIVE, False),
    Transition(31, "on_activate_failure", ACTIVATING, INACTIVE, False),
    Transition(32, "on_activate_error", ACTIVATING, ERRORPROCESSING, False),
    Transition(40, "on_deactivate_success", DEACTIVATING, INACTIVE, False),
    Transition(41, "on_deactivate_failure", DEACTIVATING, ACTIVE, False),
    Transition(42, "on_deactivate_error", DEACTIVATING, ERRORPROCESSING, False),
    Transition(50, "on_shutdown_success", SHUTTINGDOWN, FINALIZED, False),
    Transition(51, "on_shutdown_failure", SHUTTINGDOWN, FINALIZED, False),
    Transition(52, "on_shutdown_error", SHUTTINGDOWN, ERRORPROCESSING, False),
    Transition(60, "on_error_success", ERRORPROCESSING, UNCONFIGURED, False),
    Transition(61, "on_error_failure", ERRORPROCESSING, FINALIZED, False),
    Transition(62, "on_error_error", ERRORPROCESSING, FINALIZED, False),
)
TRANSITIONS_BY_ID: dict[int, Transition] = {t.id: t for t in TRANSITIONS}
EXTERNAL_TRANSITIONS = tuple(t for t in TRANSITIONS if t.external)
EXTERNAL_LABELS = ("configure", "cleanup", "activate", "deactivate", "shutdown")

# Where an external transition ends when its callback succeeds.
SUCCESS_GOAL: dict[int, int] = {
    CONFIGURE: INACTIVE,
    CLEANUP: UNCONFIGURED,
    ACTIVATE: ACTIVE,
    DEACTIVATE: INACTIVE,
    UNCONFIGURED_SHUTDOWN: FINALIZED,
    INACTIVE_SHUTDOWN: FINALIZED,
    ACTIVE_SHUTDOWN: FINALIZED,
}


class UnknownTransition(ValueError):
    """The name or id does not denote any external lifecycle transition."""


def state_label(state_id: int) -> str:
    return STATE_LABELS.get(state_id, "unknown")


def state_dict(state_id: int) -> dict:
    return {"id": state_id, "label": state_label(state_id)}


def is_primary(state_id: int) -> bool:
    return state_id in PRIMARY_STATES


def valid_transitions(state_id: int) -> list[Transition]:
    """External transitions that may be requested from ``state_id`` (none while busy)."""
    return [t for t in EXTERNAL_TRANSITIONS if t.start == state_id]


def resolve_transition(requested: str | int, state_id: int) -> Transition | None:
    """Map a label ("configure") or numeric id (1, "1") to the transition to call.

    Returns None when the transition exists but is not valid from ``state_id``;
    raises UnknownTransition when it names no external transition at all.
    "shutdown" is ambiguous by label (ids 5, 6, 7), so it resolves by the current state,
    as ``ros2 lifecycle set NODE shutdown`` does.
    """
    if isinstance(requested, bool):
        raise UnknownTransition(str(requested))
    if isinstance(requested, str) and requested.strip().isascii() and requested.strip().isdigit():
        # Only 0-9: "²" and "١" are digits to str.isdigit() (int() fails on the first), and
        # no id has more than 2 digits (int() fails past 4300).
        text = requested.strip()
        if len(text) > 9:
            raise UnknownTransition(text[:20])
        requested = int(text)
    if isinstance(requested, int):
        transition = TRANSITIONS_BY_ID.get(requested)
        if transition is None or not transition.external:
            raise UnknownTransition(str(requested))
        return transition if transition.start == state_id else None
    label = str(requested).strip().lower()
    if label not in EXTERNAL_LABELS:
        raise UnknownTransition(label)
    for transition in valid_transitions(state_id):
        if transition.label == label:
            return transition
    return None


def transition_between(start: int, goal: int) -> Transition | None:
    """The external transition leaving ``start`` into the transition state ``goal``."""
    for transition in EXTERNAL_TRANSITIONS:
        if transition.start == start and transition.goal == goal:
            return transition
    return None


def transition_graph() -> list[dict]:
    """Every edge as plain data, for the API and the graph drawing."""
    return [
        {
            "id": t.id,
            "label": t.label,
            "start": state_dict(t.start),
            "goal": state_dict(t.goal),
            "external": t.external,
        }
        for t in TRANSITIONS
    ]


# Shortest ways between primary states, as sequences of external transition labels.
_PATHS: dict[tuple[int, int], list[str]] = {
    (UNCONFIGURED, INACTIVE): ["configure"],
    (UNCONFIGURED, ACTIVE): ["configure", "activate"],
    (UNCONFIGURED, FINALIZED): ["shutdown"],
    (INACTIVE, UNCONFIGURED): ["cleanup"],
    (INACTIVE, ACTIVE): ["activate"],
    (INACTIVE, FINALIZED): ["shutdown"],
    (ACTIVE, INACTIVE): ["deactivate"],
    (ACTIVE, UNCONFIGURED): ["deactivate", "cleanup"],
    (ACTIVE, FINALIZED): ["shutdown"],
}


def path(start: int, goal: int) -> list[str] | None:
    """Transitions leading from one primary state to another ([] if already there);
    None when there is no way (out of finalized, or from a transition state)."""
    if start == goal:
        return []
    return _PATHS.get((start, goal))
