"""Commands from the site (protocol.py): each in its own task, each reply bounded in time."""
from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from dataclasses import dataclass

from ros_gateway.domain import COMMAND_DISCOVERY_WAIT_S, RosDomain
from ros_gateway.groups import GroupRunner
from ros_gateway.host_units import HostUnits
from ros_gateway.lifecycle import NodeUnreachable, available_states, available_transitions, read_state
from ros_gateway.node_driver import DELIVERY_WAIT_S, NodeDriver, NodeUnreachableRecorded
from ros_gateway.param_keeper import ParameterKeeper
from ros_gateway.parts import Core
from ros_gateway.process_usage import ProcessUsage
from ros_gateway.recovery import Recovery
from ros_gateway.registry import LiveNode, RobotInfo
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm
from ros_gateway.supervisor import Supervisor, UnknownProcess
from ros_gateway.tasks import spawn

log = logging.getLogger(__name__)

# Commands handled at once; more wait in Redis (whose queue is itself bounded).
MAX_CONCURRENT = 64


class CommandError(Exception):
    def __init__(self, code: str, message: str, **details) -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.details = details


@dataclass
class Parts:
    """What serving commands takes besides what every part shares (``core``), and nothing more."""

    core: Core
    driver: NodeDriver
    params: ParameterKeeper
    runs: GroupRunner
    supervisor: Supervisor
    units: HostUnits
    recovery: Recovery
    usage: ProcessUsage


class CommandHandler:
    def __init__(self, parts: Parts) -> None:
        self.parts = parts
        self._slots = asyncio.Semaphore(MAX_CONCURRENT)
        self._seen: deque[str] = deque(maxlen=1000)
        self.handled = 0

    @staticmethod
    def _current(command: dict) -> bool:
        """False for a command whose requester has stopped waiting."""
        return _float(command.get("deadline")) > time.time()  # also False for NaN

    def _not_carried_out(self, command: dict, why: str) -> None:
        """Put a command that will not be carried out on record (as not carried out, at the time
        the user asked); the site may have recorded it already: the fact ids make it once."""
        log.warning("did not carry out command %s of %s: %s", command.get("command"), command.get("requested_at"),
                    why)
        text = f"Not carried out: {why}; nothing was sent to {command.get('robot') or 'the robot'}."
        relay = self.parts.core.relay
        for fact in protocol.not_carried_out(relay.gateway, command, text, relay.instance):
            self.parts.core.outbox.emit_fact(fact)

    async def run(self, stopping: asyncio.Event) -> None:
        relay = self.parts.core.relay
        while not stopping.is_set():
            command = await relay.next_command()
            if command is None:
                continue
            if command["request_id"] in self._seen:
                continue  # a retried push after a lost connection: carried out once only
            self._seen.append(command["request_id"])
            if not self._current(command):
                self._not_carried_out(command, f"gateway {relay.gateway} received it after the site had stopped "
                                               "waiting for it (the gateway was frozen, overloaded or cut off)")
                continue
            # The site, once it stops waiting, claims the command as abandoned: whoever is first
            # decides, so the site can say for sure whether it was carried out.
            holder = await relay.claim(command["request_id"])
            if holder is None:
                self._not_carried_out(command, f"gateway {relay.gateway} could not confirm it to the site (Redis "
                                               "did not answer)")
                continue
            if holder == protocol.ABANDONED:
                self._not_carried_out(command, f"the site stopped waiting before gateway {relay.gateway} took it")
                continue
            if holder:
                log.warning("skipped command %s: %s has it", command.get("command"), holder)
                continue
            await self._slots.acquire()
            spawn(self._serve(command))

    async def _serve(self, command: dict) -> None:
        try:
            reply = await self.handle(command)
        except CommandError as exc:
            reply = {"ok": False, "error": {"code": exc.code, "message": exc.message}, **exc.details}
        except Exception as exc:
            log.exception("command %s failed", command.get("command"))
            reply = {"ok": False, "error": {"code": "gateway_error", "message": f"The ROS gateway failed: {exc}"}}
        finally:
            self._slots.release()
        self.handled += 1
        await self._reply(command["request_id"], reply)

    async def _reply(self, request_id: str, reply: dict) -> None:
        """The reply and the facts queued before it in one round trip; if that fails, as
        before: the reply's facts reach the stream first (a bounded wait), then the reply."""
        relay, outbox = self.parts.core.relay, self.parts.core.outbox
        key, message = relay.reply_parts(request_id, reply)
        if await outbox.reply(key, message, protocol.REPLY_TTL_S):
            return
        numbered = [f for f in reply.get("facts") or [] if isinstance(f, dict) and "seq" in f]
        if numbered:
            await outbox.delivered(max(numbered, key=lambda f: f["seq"]), DELIVERY_WAIT_S)
        await relay.reply(request_id, reply)

    async def handle(self, command: dict) -> dict:
        parts = self.parts
        name = command.get("command")
        timeout = _timeout(command.get("timeout"), parts.core.service_timeout)
        if name == protocol.PING:
            return {"ok": True, "domains": sorted(parts.core.domains), "nodes": len(parts.core.registry.nodes)}
        if name == protocol.START_RUN:
            return parts.runs.start(command.get("run"))
        if name == protocol.PROCESS_CONTROL:
            return await self.process_control(command)
        if name == protocol.PROCESS_USAGE:
            return await self.process_usage(command)
        node = await self._node(command, timeout)
        domain = parts.core.domains[node.robot.domain_id]
        first_call = self._first_call_timeout(command, domain, timeout)
        try:
            if name == protocol.GET_STATE:
                state_id = await read_state(domain, node.name, first_call)
                parts.core.registry.set_state(node, state_id)
                return {"ok": True, "state": sm.state_dict(state_id)}
            if name == protocol.GET_AVAILABLE_STATES:
                return {"ok": True, "states": await available_states(domain, node.name, first_call)}
            if name == protocol.GET_AVAILABLE_TRANSITIONS:
                return {"ok": True, "transitions": await available_transitions(domain, node.name, first_call)}
            if name == protocol.GET_TRANSITION_GRAPH:
                return {"ok": True, "graph": await available_transitions(domain, node.name, first_call, graph=True)}
            if name == protocol.GET_PARAMETERS:
                return {"ok": True, "parameters": await parts.params.listing(node, timeout)}
            if name == protocol.SET_PARAMETERS:
                values = command.get("values")
                if not isinstance(values, dict) or not values:
                    raise CommandError("bad_request", "Give the parameters to set as {name: value}.")
                results, facts = await parts.params.set(
                    node, values, timeout, str(command.get("source") or "api"), _user(command),
                    vouching=lambda name: protocol.vouching(command, name), atomic=command.get("atomic") is True,
                )
                return {"ok": True, "results": results, "facts": facts}
        except NodeUnreachable as exc:
            raise CommandError("node_unreachable", f"{node.name} on {node.robot.name} did not answer: {exc}.")
        if name == protocol.CHANGE_STATE:
            return await self.change_state(node, command, timeout, first_call)
        raise CommandError("unknown_command", f"The gateway has no command {name!r}.")

    async def process_control(self, command: dict) -> dict:
        """Start, stop or restart a process of one of the robot's launch profiles, or a container
        or systemd unit this gateway found running one of the robot's nodes: named by the profile's
        name or that attribution ("docker:NAME"), never by a pid, container id or unit of a request's."""
        robot = self._robot(command)
        action, name = command.get("action"), str(command.get("process"))
        if action not in protocol.PROCESS_ACTIONS:
            raise CommandError("unknown_action", f"{action!r} is not a process action; use one of "
                                                 f"{', '.join(protocol.PROCESS_ACTIONS)}.")
        who = {"source": str(command.get("source") or "api"), "user_id": _user(command),
               "vouching": protocol.vouching(command)}
        try:
            if protocol.HOST_PROCESS_RE.match(name):
                fact = await self.parts.units.control(robot.name, name, action, **who)
            else:
                supervisor = self.parts.supervisor
                act = {"start": supervisor.start, "stop": supervisor.stop, "restart": supervisor.restart}[action]
                fact = await act(robot.name, name, **who)
        except (UnknownProcess, LookupError):
            where = ("no node of it has been seen in that container or unit since the gateway started"
                     if protocol.HOST_PROCESS_RE.match(name) else "its launch profiles may not have reached it yet")
            raise CommandError("unknown_process", f"Gateway {self.parts.core.relay.gateway} runs no process "
                                                  f"{name!r} for {robot.name} ({where}).") from None
        if action in ("start", "restart") and fact.get("outcome") == "succeeded":
            self.parts.recovery.forgive(robot.name, name)
        return {"ok": True, "outcome": fact.get("outcome"), "message": fact.get("message"), "facts": [fact]}

    async def process_usage(self, command: dict) -> dict:
        """CPU and memory of the robot's launch profiles' processes and of its containers and units."""
        robot = self._robot(command)
        groups = {name: pid for pid, (owner, name) in self.parts.supervisor.pids().items() if owner == robot.name}
        usage = await self.parts.usage.measure(groups, self.parts.units.cgroups(robot.name))
        return {"ok": True, "usage": usage}

    def _robot(self, command: dict) -> RobotInfo:
        robot = self.parts.core.registry.robot_named(str(command.get("robot")))
        if robot is None:
            raise CommandError("robot_not_watched", f"Robot {command.get('robot')!r} is not watched (unknown or "
                                                    "disabled).")
        return robot

    async def _node(self, command: dict, timeout: float) -> LiveNode:
        robot, name = self._robot(command), command.get("node")
        node = self.parts.core.registry.find(robot.name, name)
        # Just after this gateway (or the robot's domain) started, discovery has not had its
        # chance yet: wait for it rather than call a running node "not running", bounded by the
        # domain's settling and by the requester's deadline: the wait takes the place of the
        # first call, the others keep their time.
        domain = self.parts.core.domains.get(robot.domain_id)
        give_up = _first_call_deadline(command, timeout)
        while (node is None or not node.alive) and domain is not None and domain.settling(COMMAND_DISCOVERY_WAIT_S) \
                and time.time() < give_up:
            await asyncio.sleep(0.1)
            node = self.parts.core.registry.find(robot.name, name)
        if node is None or not node.alive:
            raise CommandError("node_offline", f"{name} is not running on {robot.name} (not in its ROS graph).")
        return node

    @staticmethod
    def _first_call_timeout(command: dict, domain: RosDomain, timeout: float) -> float:
        """How long the command's first ROS call may wait for its answer. Just after this
        gateway started, robots may not answer it for a few seconds (after a kill: 1.0-3.4 s,
        docs/networks.md), so there the first call may use what the requester's deadline
        leaves beyond the other calls' time, as the wait for discovery above does."""
        if not domain.settling(COMMAND_DISCOVERY_WAIT_S):
            return timeout
        return max(timeout, _first_call_deadline(command, timeout) - time.time())

    async def change_state(self, node: LiveNode, command: dict, timeout: float, read_timeout: float) -> dict:
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
                driven = await self.parts.driver.transition(
                    node, requested, timeout, source=str(command.get("source") or "api"),
                    user_id=_user(command), run_id=str(command.get("run_id") or ""),
                    read_timeout=read_timeout, delivered_by_reply=True, vouching=protocol.vouching(command),
                )
            except NodeUnreachableRecorded as exc:
                raise CommandError("node_unreachable", str(exc), facts=[exc.fact]) from None
        result = driven.result
        return {
            "ok": True,
            "outcome": result.outcome,
            "transition": result.transition.as_dict() if result.transition else None,
            "from": sm.state_dict(result.start_state),
            "to": sm.state_dict(result.result_state) if result.result_state is not None else None,
            "duration_ms": round(result.duration_ms, 2),
            "message": result.message,
            "valid_transitions": result.valid,
            "fact_id": driven.record["id"],
            "facts": driven.facts,
        }


def _first_call_deadline(command: dict, timeout: float) -> float:
    """When (epoch seconds) the command's first call must be over for the others to keep
    their ``timeout`` each within the requester's deadline."""
    return _float(command.get("deadline")) - (protocol.CALLS_PER_COMMAND - 1) * timeout


def _timeout(value: object, default: float) -> float:
    """The command's service timeout, if it is a sane number of seconds, else the default."""
    timeout = _float(value)
    return timeout if 0 < timeout <= 60 else default


def _float(value: object) -> float:
    """The value as a number, 0.0 if it is none."""
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return 0.0


def _user(command: dict) -> int | None:
    user_id = command.get("user_id")
    return user_id if isinstance(user_id, int) and not isinstance(user_id, bool) else None
