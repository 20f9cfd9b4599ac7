"""Lifecycle service calls on one node, each bounded by a timeout (the one way every path
carries out a transition, with its audit fact, is node_driver.py).

``perform_transition`` is the heart of the product's safety promise: it checks the
transition against the node's real current state, calls it, and after a failure or a
timeout re-reads the state before it reports, because the node may have moved anyway
(Nav2's lifecycle manager reports failure without looking).
"""
from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field
from typing import Any, Callable

from lifecycle_msgs.msg import Transition as TransitionMsg
from lifecycle_msgs.srv import ChangeState, GetAvailableStates, GetAvailableTransitions, GetState

from ros_gateway.domain import RosDomain, ServiceTimeout, ServiceUnavailable
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm


class NodeUnreachable(Exception):
    """The node did not answer before anything was sent to it."""


async def read_state(domain: RosDomain, fqn: str, timeout: float) -> int:
    try:
        response = await domain.call(fqn, "get_state", GetState, GetState.Request(), timeout)
    except (ServiceTimeout, ServiceUnavailable) as exc:
        raise NodeUnreachable(str(exc)) from None
    return int(response.current_state.id)


async def available_states(domain: RosDomain, fqn: str, timeout: float) -> list[dict]:
    try:
        response = await domain.call(
            fqn, "get_available_states", GetAvailableStates, GetAvailableStates.Request(), timeout
        )
    except (ServiceTimeout, ServiceUnavailable) as exc:
        raise NodeUnreachable(str(exc)) from None
    return [{"id": int(s.id), "label": s.label} for s in response.available_states]


async def available_transitions(domain: RosDomain, fqn: str, timeout: float, graph: bool = False) -> list[dict]:
    """The node's own answer: currently valid transitions, or the whole graph."""
    service = "get_transition_graph" if graph else "get_available_transitions"
    try:
        response = await domain.call(fqn, service, GetAvailableTransitions, GetAvailableTransitions.Request(), timeout)
    except (ServiceTimeout, ServiceUnavailable) as exc:
        raise NodeUnreachable(str(exc)) from None
    return [
        {
            "id": int(d.transition.id),
            "label": d.transition.label,
            "start": {"id": int(d.start_state.id), "label": d.start_state.label},
            "goal": {"id": int(d.goal_state.id), "label": d.goal_state.label},
            "external": bool(getattr(sm.TRANSITIONS_BY_ID.get(int(d.transition.id)), "external", False)),
        }
        for d in response.available_transitions
    ]


# While a transition runs, how often the node's process (processes.py) and its transition events
# are looked at.
PROCESS_POLL_S = 0.1
# How long the answer to change_state is still awaited once the node's transition events told its
# end (it follows them within milliseconds): after that it counts as lost on the way, which DDS
# does to a response when the node has not yet matched the caller's answer reader (domain.py).
ANSWER_AFTER_EVENTS_S = 0.5
LEFT_GRAPH = "its node left the ROS graph"
# () -> how the node's process went ("exited", ...), or None while it is there.
ProcessGone = Callable[[], "str | None"]
# (transition id) -> the state our request's transition events say it ended in, or None yet.
EndedAs = Callable[[int], "int | None"]


@dataclass
class TransitionResult:
    outcome: str  # succeeded | failed | rejected | timed_out | process_lost
    transition: sm.Transition | None
    start_state: int
    result_state: int | None  # None: could not be read (node still busy or gone)
    duration_ms: float
    message: str = ""
    valid: list[dict] = field(default_factory=list)
    process_gone: str | None = None  # process_lost: how (LEFT_GRAPH, or it is known to have ended)
    read: bool = False  # result_state was read from the node after the call (the newest there is then)


async def perform_transition(
    domain: RosDomain,
    fqn: str,
    requested: str | int,
    timeout: float,
    on_send=None,
    known_state: int | None = None,
    process_gone: ProcessGone | None = None,
    read_timeout: float | None = None,
    ended_as: EndedAs | None = None,
) -> TransitionResult:
    """Check, call and verify one transition. Raises NodeUnreachable and sm.UnknownTransition.

    ``on_send(transition)`` runs just before the request leaves, so the caller can tell the
    node's transition events that follow apart from other tools' transitions.
    ``known_state``: the state the caller has just read from the node itself (a group run
    step by step), which spares one get_state call.
    ``process_gone``: looked at while the call runs; once it says the node's process went,
    the call ends at once as ``process_lost`` (its answer would never come).
    ``read_timeout``: the first state read's own bound, when it is not ``timeout``.
    ``ended_as``: what the node's transition events say our request ended in; once they told it,
    an answer that does not follow within ANSWER_AFTER_EVENTS_S is taken as lost, and the
    outcome is the events' (not a time-out ANSWER_AFTER_EVENTS_S later).
    """
    if known_state is not None:
        start_state = known_state
    else:
        start_state = await read_state(domain, fqn, timeout if read_timeout is None else read_timeout)
    transition = sm.resolve_transition(requested, start_state)
    if transition is None:
        valid = [t.as_dict() for t in sm.valid_transitions(start_state)]
        names = ", ".join(t["label"] for t in valid) or "none (the node is busy or finalized)"
        return TransitionResult(
            "rejected",
            None,
            start_state,
            start_state,
            0.0,
            f"'{requested}' is not possible from state {sm.state_label(start_state)}; valid now: {names}.",
            valid,
        )
    if on_send is not None:
        on_send(transition)
    request = ChangeState.Request(transition=TransitionMsg(id=transition.id, label=transition.label))
    began = time.perf_counter()
    told = (lambda: ended_as(transition.id)) if ended_as is not None else None
    try:
        response, gone, ended = await _call_watching(domain, fqn, request, timeout, process_gone, told)
    except (ServiceTimeout, ServiceUnavailable):
        gone = process_gone() if process_gone is not None else None
        if gone is None:
            duration = (time.perf_counter() - began) * 1000
            now_state = await _reread(domain, fqn, timeout)
            where = (
                f"it is now {sm.state_label(now_state)}" if now_state is not None
                else "its state could not be read either (still busy, or gone)"
            )
            return TransitionResult(
                "timed_out", transition, start_state, now_state, duration,
                f"{transition.label} did not answer within {timeout:g} s; {where}.", read=True,
            )
        response, ended = None, None
    duration = (time.perf_counter() - began) * 1000
    if ended is not None:
        lost = (f"Its answer was lost on the way (the node's transition events told the outcome; "
                f"{transition.label} ended {sm.state_label(ended)}).")
        if ended == sm.SUCCESS_GOAL[transition.id]:
            return TransitionResult("succeeded", transition, start_state, ended, duration, lost)
        return TransitionResult("failed", transition, start_state, ended, duration,
                                f"{_failure_message(transition, start_state, ended)} {lost}")
    if gone is not None:
        message = (f"The node's process ended during {transition.label} ({gone}, {duration / 1000:.1f} s after "
                   "the request): the transition's answer will never come. Its supervisor may start it again; "
                   "a new instance starts unconfigured.")
        return TransitionResult(protocol.PROCESS_LOST, transition, start_state, None, duration, message,
                                process_gone=gone)
    if response.success:
        return TransitionResult("succeeded", transition, start_state, sm.SUCCESS_GOAL[transition.id], duration)
    now_state = await _reread(domain, fqn, timeout)
    return TransitionResult(
        "failed", transition, start_state, now_state, duration, _failure_message(transition, start_state, now_state),
        read=True,
    )


async def _call_watching(domain: RosDomain, fqn: str, request: Any, timeout: float,
                         process_gone: ProcessGone | None,
                         told: Callable[[], int | None] | None) -> tuple[Any, str | None, int | None]:
    """(change_state's answer, None, None); or (None, how it went, None) as soon as the node's
    process is seen gone; or (None, None, the end state) when the node's transition events told
    it and the answer did not follow within ANSWER_AFTER_EVENTS_S. Raises ServiceTimeout and
    ServiceUnavailable as RosDomain.call does."""
    call = asyncio.ensure_future(domain.call(fqn, "change_state", ChangeState, request, timeout))
    if process_gone is None and told is None:
        return await call, None, None
    told_at: float | None = None
    try:
        while True:
            done, _ = await asyncio.wait({call}, timeout=PROCESS_POLL_S)
            if done:
                return call.result(), None, None
            gone = process_gone() if process_gone is not None else None
            if gone is not None:
                return None, gone, None
            ended = told() if told is not None else None
            if ended is not None:
                told_at = time.monotonic() if told_at is None else told_at
                if time.monotonic() - told_at >= ANSWER_AFTER_EVENTS_S:
                    return None, None, ended
    finally:
        if not call.done():
            call.cancel()
            await asyncio.gather(call, return_exceptions=True)


async def _reread(domain: RosDomain, fqn: str, timeout: float) -> int | None:
    try:
        return await read_state(domain, fqn, timeout)
    except NodeUnreachable:
        return None


def _failure_message(transition: sm.Transition, start_state: int, now_state: int | None) -> str:
    callback = f"on_{transition.label}"
    if now_state == start_state:
        return (
            f"The node's {callback} callback returned FAILURE; "
            f"the node stayed {sm.state_label(start_state)}."
        )
    if now_state in (sm.UNCONFIGURED, sm.FINALIZED):
        return (
            f"The node's {callback} callback raised an error; error processing "
            f"brought the node to {sm.state_label(now_state)}."
        )
    if now_state is None:
        return f"The node's {callback} callback did not succeed and its state could not be read afterwards."
    return f"The node's {callback} callback did not succeed; the node is now {sm.state_label(now_state)}."
