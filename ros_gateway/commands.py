"""Commands from the site (protocol.py): each in its own task, each reply bounded in time."""
from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from datetime import datetime, timezone
from typing import TYPE_CHECKING

from ros_gateway import protocol, store
from ros_gateway import state_machine as sm
from ros_gateway.lifecycle import (
    NodeUnreachable,
    available_states,
    available_transitions,
    perform_transition,
    read_state,
)
from ros_gateway.store import db

if TYPE_CHECKING:
    from ros_gateway.service import Gateway, LiveNode

log = logging.getLogger(__name__)

# Commands handled at once; more wait in Redis (whose queue is itself bounded).
MAX_CONCURRENT = 64
# How long a failed transition waits for the node's own error lines to arrive on /rosout.
REASON_WAIT_S = 0.5


class CommandError(Exception):
    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message


class CommandHandler:
    def __init__(self, gateway: "Gateway") -> None:
        self.gateway = gateway
        self._slots = asyncio.Semaphore(MAX_CONCURRENT)
        self._seen: deque[str] = deque(maxlen=1000)
        self.handled = 0

    @staticmethod
    def _current(command: dict) -> bool:
        """False (and logged) for a command whose requester has stopped waiting."""
        try:
            deadline = float(command.get("deadline", 0))
        except (TypeError, ValueError):
            deadline = 0.0
        if deadline > time.time():  # also False for NaN
            return True
        log.warning("dropped command %s: its requester stopped waiting", command.get("command"))
        return False

    async def run(self, stopping: asyncio.Event) -> None:
        while not stopping.is_set():
            command = await self.gateway.relay.next_command(wait=1.0)
            if command is None:
                continue
            if not self._current(command):
                continue
            if command["request_id"] in self._seen:
                continue  # a retried push after a lost connection: carried out once only
            self._seen.append(command["request_id"])
            await self._slots.acquire()
            self.gateway.spawn(self._serve(command))

    async def _serve(self, command: dict) -> None:
        try:
            reply = await self.handle(command)
        except CommandError as exc:
            reply = {"ok": False, "error": {"code": exc.code, "message": exc.message}}
        except Exception as exc:
            log.exception("command %s failed", command.get("command"))
            reply = {"ok": False, "error": {"code": "gateway_error", "message": f"The ROS gateway failed: {exc}"}}
        finally:
            self._slots.release()
        self.handled += 1
        await self.gateway.relay.reply(command["request_id"], reply)

    async def handle(self, command: dict) -> dict:
        name = command.get("command")
        timeout = float(command.get("timeout") or self.gateway.config["SERVICE_TIMEOUT"])
        if name == protocol.PING:
            return {"ok": True, "domains": sorted(self.gateway.domains), "nodes": len(self.gateway.nodes)}
        node = self._node(command)
        domain = self.gateway.domains[node.robot.domain_id]
        try:
            if name == protocol.GET_STATE:
                state_id = await read_state(domain, node.name, timeout)
                await self.gateway.set_state(node, state_id)
                return {"ok": True, "state": sm.state_dict(state_id)}
            if name == protocol.GET_AVAILABLE_STATES:
                return {"ok": True, "states": await available_states(domain, node.name, timeout)}
            if name == protocol.GET_AVAILABLE_TRANSITIONS:
                return {"ok": True, "transitions": await available_transitions(domain, node.name, timeout)}
            if name == protocol.GET_TRANSITION_GRAPH:
                return {"ok": True, "graph": await available_transitions(domain, node.name, timeout, graph=True)}
        except NodeUnreachable as exc:
            raise CommandError("node_unreachable", f"{node.name} on {node.robot.name} did not answer: {exc}.")
        if name == protocol.CHANGE_STATE:
            return await self.change_state(node, command, timeout)
        raise CommandError("unknown_command", f"The gateway has no command {name!r}.")

    def _node(self, command: dict) -> "LiveNode":
        robot, name = command.get("robot"), command.get("node")
        if not any(r.name == robot for r in self.gateway.robots.values()):
            raise CommandError("robot_not_watched", f"Robot {robot!r} is not watched (unknown or disabled).")
        node = self.gateway.find_node(robot, name)
        if node is None or not node.alive:
            raise CommandError("node_offline", f"{name} is not running on {robot} (not in its ROS graph).")
        return node

    async def change_state(self, node: "LiveNode", command: dict, timeout: float) -> dict:
        requested = command.get("transition")
        try:
            sm.resolve_transition(requested, sm.UNCONFIGURED)  # only checks that the name exists
        except sm.UnknownTransition:
            raise CommandError(
                "unknown_transition",
                f"{requested!r} is not a lifecycle transition; use one of {', '.join(sm.EXTERNAL_LABELS)}.",
            ) from None
        domain = self.gateway.domains[node.robot.domain_id]
        if node.lock.locked():
            # Queueing behind a running transition would act on a state the requester never saw.
            raise CommandError(
                "node_busy",
                f"Another transition of {node.name} on {node.robot.name} is still in progress; "
                "try again when it has finished.",
            )
        async with node.lock:  # one transition per node at a time
            requested_at = datetime.now(timezone.utc)
            try:
                result = await perform_transition(
                    domain, node.name, requested, timeout, on_send=lambda t: self._claim(node, t)
                )
            except NodeUnreachable as exc:
                message = f"{node.name} on {node.robot.name} did not answer ({exc}); nothing was sent to it."
                await db(store.record_transition)(
                    node_id=node.row.id, robot=node.robot, node_name=node.name, transition=None,
                    requested_label=str(requested), start_state=node.state_id, result_state=None,
                    outcome="rejected", source=command.get("source") or "api", requested_at=requested_at,
                    completed_at=datetime.now(timezone.utc), user_id=command.get("user_id"), error=message,
                )
                raise CommandError("node_unreachable", message) from None
            if result.result_state is not None:
                if result.transition is not None and node.tracker.commanded == result.transition.id:
                    node.tracker.settled = result.transition.id  # its beginning is yet to come
                await self.gateway.set_state(node, result.result_state)
            if result.outcome == "failed":
                result.message = await self._with_reason(node, requested_at, result.message)
            record = await db(store.record_transition)(
                node_id=node.row.id,
                robot=node.robot,
                node_name=node.name,
                transition=result.transition,
                requested_label=str(requested),
                start_state=result.start_state,
                result_state=result.result_state,
                outcome=result.outcome,
                source=command.get("source") or "api",
                requested_at=requested_at,
                completed_at=datetime.now(timezone.utc),
                user_id=command.get("user_id"),
                error=result.message,
                run_id=command.get("run_id") or "",
            )
        await self.gateway.publish_record(node, record)
        return {
            "ok": True,
            "outcome": result.outcome,
            "transition": result.transition.as_dict() if result.transition else None,
            "from": sm.state_dict(result.start_state),
            "to": sm.state_dict(result.result_state) if result.result_state is not None else None,
            "duration_ms": round(result.duration_ms, 2),
            "message": result.message,
            "valid_transitions": result.valid,
            "record_id": record["id"],
        }

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
