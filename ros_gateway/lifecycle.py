"""Lifecycle service calls on one node, each bounded by a timeout, and the one way every
path (a request, a group run, recovery) carries out a transition: ``NodeDriver``.

``perform_transition`` is the heart of the product's safety promise: it checks the
transition against the node's real current state, calls it, and after a failure or a
timeout re-reads the state before it reports, because the node may have moved anyway
(Nav2's lifecycle manager reports failure without looking). ``NodeDriver.transition`` adds
the rest: the state taken over, the node's own reason for a failure, and the audit fact.
"""
from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any, Callable

from lifecycle_msgs.msg import Transition as TransitionMsg
from lifecycle_msgs.srv import ChangeState, GetAvailableStates, GetAvailableTransitions, GetState

from ros_gateway.domain import RosDomain, ServiceTimeout, ServiceUnavailable
from ros_gateway.logs import LogPipeline
from ros_gateway.outbox import Outbox
from ros_gateway.processes import LocalProcesses
from ros_gateway.registry import LiveNode, NodeRegistry, participants
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


# While a transition runs, how often the node's process is looked at (processes.py).
PROCESS_POLL_S = 0.1
LEFT_GRAPH = "its node left the ROS graph"
# () -> how the node's process went ("exited", ...), or None while it is there.
ProcessGone = Callable[[], "str | None"]


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


async def perform_transition(
    domain: RosDomain,
    fqn: str,
    requested: str | int,
    timeout: float,
    on_send=None,
    known_state: int | None = None,
    process_gone: ProcessGone | None = None,
    read_timeout: float | None = None,
) -> TransitionResult:
    """Check, call and verify one transition. Raises NodeUnreachable and sm.UnknownTransition.

    ``on_send(transition)`` runs just before the request leaves, so the caller can tell the
    node's transition events that follow apart from other tools' transitions.
    ``known_state``: the state the caller has just read from the node itself (a group run
    step by step), which spares one get_state call.
    ``process_gone``: looked at while the call runs; once it says the node's process went,
    the call ends at once as ``process_lost`` (its answer would never come).
    ``read_timeout``: the first state read's own bound, when it is not ``timeout``.
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
    try:
        response, gone = await _call_watching(domain, fqn, request, timeout, process_gone)
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
                f"{transition.label} did not answer within {timeout:g} s; {where}.",
            )
        response = None
    duration = (time.perf_counter() - began) * 1000
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
        "failed", transition, start_state, now_state, duration, _failure_message(transition, start_state, now_state)
    )


async def _call_watching(domain: RosDomain, fqn: str, request: Any, timeout: float,
                         process_gone: ProcessGone | None) -> tuple[Any, str | None]:
    """change_state's answer, or (None, how it went) as soon as the node's process is seen gone.
    Raises ServiceTimeout and ServiceUnavailable as RosDomain.call does."""
    call = asyncio.ensure_future(domain.call(fqn, "change_state", ChangeState, request, timeout))
    if process_gone is None:
        return await call, None
    try:
        while True:
            done, _ = await asyncio.wait({call}, timeout=PROCESS_POLL_S)
            if done:
                return call.result(), None
            gone = process_gone()
            if gone is not None:
                return None, gone
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


# How long a failed transition waits for the node's own error lines to arrive on /rosout.
REASON_WAIT_S = 0.5
# How long the answer to a request waits for its audit fact to be in Redis.
DELIVERY_WAIT_S = 2.0


@dataclass
class Driven:
    """A transition's result with the facts that report it (state first, then the audit)."""

    result: TransitionResult
    record: dict
    facts: list[dict]


class NodeUnreachableRecorded(NodeUnreachable):
    """Nothing could be sent to the node; the attempt was reported (``fact``)."""

    def __init__(self, message: str, fact: dict) -> None:
        super().__init__(message)
        self.fact = fact


class NodeDriver:
    def __init__(self, domains: dict[int, RosDomain], registry: NodeRegistry, outbox: Outbox, logs: LogPipeline,
                 service_timeout: float, processes: LocalProcesses | None = None) -> None:
        self.domains, self.registry, self.outbox, self.logs = domains, registry, outbox, logs
        self.service_timeout = service_timeout
        self.processes = processes or LocalProcesses()

    async def transition(
        self, node: LiveNode, requested, timeout: float, *, source: str, user_id: int | None = None,
        run_id: str = "", known_state: int | None = None, read_timeout: float | None = None,
        delivered_by_reply: bool = False, vouching: dict | None = None,
    ) -> Driven:
        """Carry out one transition; the caller holds ``node.lock``. Raises
        NodeUnreachableRecorded (reported too) when nothing could be sent. Returns once its
        audit fact is in Redis (bounded), unless ``delivered_by_reply``: a command's reply takes
        its facts along (commands.py), so waiting for the flusher first would cost a round trip."""
        # Until it is reported, what becomes of the node's process is this transition's to say
        # (discovery keeps out of it: one record, and no restart taken for another one's).
        node.in_transition = True
        try:
            driven = await self._transition(node, requested, timeout, source=source, user_id=user_id,
                                            run_id=run_id, known_state=known_state, read_timeout=read_timeout,
                                            vouching=vouching or {})
        except NodeUnreachableRecorded as exc:
            if not delivered_by_reply:
                await self.outbox.delivered(exc.fact, DELIVERY_WAIT_S)
            raise
        finally:
            node.in_transition = False
        if not delivered_by_reply:
            await self.outbox.delivered(driven.record, DELIVERY_WAIT_S)
        return driven

    async def _transition(self, node: LiveNode, requested, timeout: float, *, source: str, user_id: int | None,
                          run_id: str, known_state: int | None, read_timeout: float | None,
                          vouching: dict) -> Driven:
        domain = self.domains[node.robot.domain_id]
        requested_at = datetime.now(timezone.utc)
        # A command of the site carries its grant, and the record the request's id (protocol.vouching).
        audit = dict(robot=node.robot.name, node=node.name, source=source, user_id=user_id, run_id=run_id,
                     requested_at=requested_at.isoformat(), **vouching)
        try:
            result = await perform_transition(domain, node.name, requested, timeout,
                                              on_send=lambda t: self._claim(node, t), known_state=known_state,
                                              process_gone=self._process_gone(node, domain),
                                              read_timeout=read_timeout)
        except NodeUnreachable as exc:
            message = f"{node.name} on {node.robot.name} did not answer ({exc}); nothing was sent to it."
            fact = self.outbox.emit(
                protocol.TRANSITION, **audit, transition_id=None,
                transition_label=protocol.transition_word(requested),
                start_state=node.state_id, result_state=None, outcome="rejected",
                completed_at=datetime.now(timezone.utc).isoformat(), error=message,
            )
            raise NodeUnreachableRecorded(message, fact) from None
        if result.transition is not None and node.tracker.commanded == result.transition.id:
            node.tracker.settled = result.transition.id  # its beginning is yet to come
        facts = []
        if result.outcome == protocol.PROCESS_LOST and node.alive:
            domain.forget_node(node.name)
            ended = result.process_gone != LEFT_GRAPH  # exited, or replaced: the old one lingers dead
            facts.append(self.registry.vanished(node, reason=protocol.PROCESS_LOST, ended=ended).fact)
        if result.outcome in ("failed", protocol.PROCESS_LOST):
            result.message = await self._with_reason(node, requested_at, result.message)
        if result.result_state is not None:
            change = self.registry.set_state(node, result.result_state)
            # The state goes with the answer even when a transition event reported it first,
            # so that the site's record of the node is right before the requester hears back.
            state_fact = change.fact if change is not None else None
            facts.append(state_fact or self.outbox.emit(protocol.NODE_STATE, robot=node.robot.name, node=node.name,
                                                        state_id=result.result_state))
        transition = result.transition
        fact = self.outbox.emit(
            protocol.TRANSITION, **audit,
            transition_id=transition.id if transition else None,
            transition_label=transition.label if transition else protocol.transition_word(requested),
            start_state=result.start_state, result_state=result.result_state, outcome=result.outcome,
            completed_at=datetime.now(timezone.utc).isoformat(), error=result.message,
        )
        facts.append(fact)
        return Driven(result, fact, facts)

    def _process_gone(self, node: LiveNode, domain: RosDomain) -> ProcessGone:
        """How the node's process went, once it has: it exited (seen on this host), it left the
        ROS graph, or a process of another DDS participant now publishes its transition events."""
        before = node.live

        def gone() -> str | None:
            if not before:
                return None  # its endpoints were never seen: nothing to compare with
            if self.processes.all_ended(domain.domain_id, before):
                return "it exited, as seen on this host"
            now = participants(domain.incarnation(node.name))
            if not now & before:
                return LEFT_GRAPH
            if now - before - node.departed:
                return "a new process now runs under its name"
            return None

        return gone

    def _claim(self, node: LiveNode, transition: sm.Transition) -> None:
        """Mark the transition about to be sent as ours, so its events are not 'external'."""
        node.tracker.commanded = transition.id
        loop = asyncio.get_running_loop()

        def release() -> None:
            if node.tracker.commanded == transition.id:
                node.tracker.commanded = None
            if node.tracker.settled == transition.id:
                node.tracker.settled = None

        loop.call_later(max(2.0, 2 * self.service_timeout), release)

    async def _with_reason(self, node: LiveNode, since: datetime, message: str) -> str:
        """Add what the node itself logged at ERROR/FATAL during the transition."""
        deadline = time.monotonic() + REASON_WAIT_S
        while True:
            self.logs.collect()
            errors = self.logs.errors_since(node.key, since)
            if errors or time.monotonic() >= deadline:
                break
            await asyncio.sleep(0.05)
        if not errors:
            return message
        lines = "; ".join(e.message for e in errors[-3:])
        return f"{message} The node said: {lines}"
