"""Commands from the site (protocol.py): each in its own task, each reply bounded in time."""
from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from typing import TYPE_CHECKING

from ros_gateway.lifecycle import (
    NodeUnreachable,
    available_states,
    available_transitions,
    read_state,
)
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm

if TYPE_CHECKING:
    from ros_gateway.service import Gateway, LiveNode

log = logging.getLogger(__name__)

# Commands handled at once; more wait in Redis (whose queue is itself bounded).
MAX_CONCURRENT = 64


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
        if name == protocol.START_RUN:
            return await self.gateway.groups.start(str(command.get("run_id", "")))
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
            if name == protocol.GET_PARAMETERS:
                return {"ok": True, "parameters": await self.gateway.params.listing(node, timeout)}
            if name == protocol.SET_PARAMETERS:
                values = command.get("values")
                if not isinstance(values, dict) or not values:
                    raise CommandError("bad_request", "Give the parameters to set as {name: value}.")
                results = await self.gateway.params.set(
                    node, values, timeout, command.get("source") or "api", command.get("user_id")
                )
                return {"ok": True, "results": results}
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
        if node.lock.locked():
            # Queueing behind a running transition would act on a state the requester never saw.
            raise CommandError(
                "node_busy",
                f"Another transition of {node.name} on {node.robot.name} is still in progress; "
                "try again when it has finished.",
            )
        async with node.lock:  # one transition per node at a time
            try:
                result, record = await self.gateway.driver.transition(
                    node, requested, timeout, source=command.get("source") or "api",
                    user_id=command.get("user_id"), run_id=command.get("run_id") or "",
                )
            except NodeUnreachable as exc:
                raise CommandError("node_unreachable", str(exc)) from None
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
