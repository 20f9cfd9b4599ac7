"""The one way every path (a request, a group run, recovery) carries out a transition:
``NodeDriver.transition`` runs lifecycle.perform_transition and adds the rest: the state taken
over, the node's own reason for a failure, and the audit fact."""
from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass
from datetime import datetime, timezone

from ros_gateway.domain import RosDomain
from ros_gateway.lifecycle import LEFT_GRAPH, NodeUnreachable, ProcessGone, TransitionResult, perform_transition
from ros_gateway.logs import LogPipeline
from ros_gateway.parts import Core
from ros_gateway.registry import LiveNode, participants
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm

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
    def __init__(self, core: Core, logs: LogPipeline) -> None:
        self.domains, self.registry, self.outbox, self.logs = core.domains, core.registry, core.outbox, logs
        self.service_timeout = core.service_timeout
        self.processes = core.processes

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
                                            vouching=vouching or {}, by_reply=delivered_by_reply)
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
                          vouching: dict, by_reply: bool) -> Driven:
        domain = self.domains[node.robot.domain_id]
        requested_at = datetime.now(timezone.utc)
        # A command of the site carries its grant, and the record the request's id (protocol.vouching).
        audit = dict(robot=node.robot.name, node=node.name, source=source, user_id=user_id, run_id=run_id,
                     requested_at=requested_at.isoformat(), **vouching)
        try:
            result = await perform_transition(domain, node.name, requested, timeout,
                                              on_send=lambda t: self._claim(node, t), known_state=known_state,
                                              process_gone=self._process_gone(node, domain),
                                              read_timeout=read_timeout, ended_as=node.tracker.ended_as)
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
            # Its beginning is yet to come: known as ours by ``settled`` (the next may be claimed meanwhile).
            node.tracker.settled, node.tracker.commanded = result.transition.id, None
        facts = []
        if result.outcome == protocol.PROCESS_LOST and node.alive:
            domain.forget_node(node.name, keep=True)
            ended = result.process_gone != LEFT_GRAPH  # exited, or replaced: the old one lingers dead
            facts.append(self.registry.vanished(node, reason=protocol.PROCESS_LOST, ended=ended).fact)
        if result.result_state is not None:
            # Another tool's transition that began after ours ended (its events handled before this
            # reply) is newer than what our request left: the state stays as the events told. A
            # state read after the call is the newest there is, whatever came before.
            overtaken = (not result.read and result.transition is not None
                         and node.tracker.overtaken(result.transition.id))
            change = None if overtaken else self.registry.set_state(node, result.result_state)
            state_fact = change.fact if change is not None else None
            if state_fact is None and by_reply:
                # A reply carries the state even when a transition event reported it first, so that
                # the site's record of the node is right before the requester hears back. A run's
                # step has nobody waiting: the event's fact, in the stream before this, is enough.
                state_fact = self.outbox.emit(protocol.NODE_STATE, robot=node.robot.name, node=node.name,
                                              state_id=node.state_id if overtaken else result.result_state)
            if state_fact is not None:
                facts.append(state_fact)
        if result.outcome in ("failed", protocol.PROCESS_LOST):  # (after the state: this waits up to 0.5 s)
            result.message = await self._with_reason(node, requested_at, result.message)
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
        node.tracker.ended = None  # (its events will tell this one's end)
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
