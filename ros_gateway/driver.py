"""One transition of one node, as every path uses it (a request, a group run, recovery):
checked and called (lifecycle.perform_transition), the state taken over, the node's own
reason added to a failure, and the attempt written to the audit log."""
from __future__ import annotations

import asyncio
import time
from datetime import datetime, timezone
from typing import TYPE_CHECKING

from ros_gateway import store
from ros_gateway.lifecycle import NodeUnreachable, TransitionResult, perform_transition
from ros_gateway.shared import state_machine as sm
from ros_gateway.store import db

if TYPE_CHECKING:
    from ros_gateway.service import Gateway, LiveNode

# How long a failed transition waits for the node's own error lines to arrive on /rosout.
REASON_WAIT_S = 0.5


class NodeDriver:
    def __init__(self, gateway: "Gateway") -> None:
        self.gateway = gateway

    async def transition(
        self, node: "LiveNode", requested, timeout: float, *, source: str, user_id: int | None = None,
        run_id: str = "", known_state: int | None = None,
    ) -> tuple[TransitionResult, dict]:
        """Carry out one transition; the caller holds ``node.lock``. Returns the result and
        its audit record; raises NodeUnreachable (recorded too) when nothing could be sent."""
        domain = self.gateway.domains[node.robot.domain_id]
        requested_at = datetime.now(timezone.utc)
        audit = dict(node_id=node.row.id, node_key=node.key, robot=node.robot, node_name=node.name,
                     requested_label=str(requested),
                     source=source, requested_at=requested_at, user_id=user_id, run_id=run_id)
        try:
            result = await perform_transition(domain, node.name, requested, timeout,
                                              on_send=lambda t: self._claim(node, t), known_state=known_state)
        except NodeUnreachable as exc:
            message = f"{node.name} on {node.robot.name} did not answer ({exc}); nothing was sent to it."
            await db(store.record_transition)(
                **audit, transition=None, start_state=node.state_id, result_state=None, outcome="rejected",
                completed_at=datetime.now(timezone.utc), error=message,
            )
            raise NodeUnreachable(message) from None
        if result.transition is not None and node.tracker.commanded == result.transition.id:
            node.tracker.settled = result.transition.id  # its beginning is yet to come
        if result.outcome == "failed":
            result.message = await self._with_reason(node, requested_at, result.message)
        # The new state (pushed and stored) and the audit record are written side by side.
        new_state = self.gateway.set_state(node, result.result_state) if result.result_state is not None else None
        record, _ = await asyncio.gather(
            db(store.record_transition)(
                **audit, transition=result.transition, start_state=result.start_state,
                result_state=result.result_state, outcome=result.outcome,
                completed_at=datetime.now(timezone.utc), error=result.message,
            ),
            new_state or asyncio.sleep(0),
        )
        # Pages showing the history get the record after the requester has its answer.
        self.gateway.spawn(self.gateway.publish_record(node, record))
        return result, record

    def _claim(self, node: "LiveNode", transition: sm.Transition) -> None:
        """Mark the transition about to be sent as ours, so its events are not 'external'."""
        node.tracker.commanded = transition.id
        loop = asyncio.get_running_loop()

        def release() -> None:
            if node.tracker.commanded == transition.id:
                node.tracker.commanded = None
            if node.tracker.settled == transition.id:
                node.tracker.settled = None

        loop.call_later(max(2.0, 2 * self.gateway.config["SERVICE_TIMEOUT"]), release)

    async def _with_reason(self, node: "LiveNode", since: datetime, message: str) -> str:
        """Add what the node itself logged at ERROR/FATAL during the transition."""
        deadline = time.monotonic() + REASON_WAIT_S
        while True:
            await self.gateway.logs.flush()
            errors = self.gateway.logs.errors_since(node.key, since)
            if errors or time.monotonic() >= deadline:
                break
            await asyncio.sleep(0.05)
        if not errors:
            return message
        lines = "; ".join(e.message for e in errors[-3:])
        return f"{message} The node said: {lines}"
