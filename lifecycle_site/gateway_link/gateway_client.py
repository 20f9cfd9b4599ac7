"""The site's side of talking to a gateway: one command on that gateway's queue, one reply,
a bounded wait. A gateway that is offline is not asked at all (GatewayOffline, at once).

A command the gateway has not answered in time is settled, not left in doubt: the site
claims it as abandoned (protocol.claim_key), and a gateway carries a command out only if it
claimed it first. So the answer says plainly that the command was not carried out, or that
the gateway had taken it (and whether that gateway's process is gone since).
"""
from __future__ import annotations

import json
import math
import time
import uuid
from datetime import datetime, timezone
from typing import Any

import redis
from django.conf import settings
from django.utils.translation import gettext_noop

from lifecycle_site.gateway_link import attribution, gateways, presence, redis_guard
from lifecycle_site.gateway_link import gateway_input as checks
from lifecycle_site.gateway_link.gateways import MAX_SERVICE_TIMEOUT, channel_prefix
from lifecycle_site.refusal import Refusal, both, in_english
from ros_gateway.shared import protocol

__all__ = ["GatewayError", "GatewayOffline", "GatewayNoAnswer", "call_gateway", "channel_prefix",
           "MAX_SERVICE_TIMEOUT"]

# The largest reply read (a node's parameter listing is the largest an honest gateway sends).
MAX_REPLY_BYTES = 4 * 1024 * 1024
# The reply is awaited in blocking pops of at most this long, so that a Redis that stops
# answering or a gateway whose process ended is noticed within about a second.
WAIT_SLICE_S = 1.0


class GatewayError(Refusal):
    """A command could not be carried out; ``code`` and ``message`` are shown to the user
    (``english``: the message as an audit record or a run's summary stores it).

    ``facts`` are what the gateway (or the site, for a command it withdrew) reported along with
    the refusal (an audit record of the attempt, say): the caller applies them like those of a
    successful reply. ``carried_out`` is False when nothing reached the robot, None when that
    is not known. ``requested_at`` is when the user asked."""

    status = 502

    def __init__(self, code: str, message: str, facts: list | None = None, *, carried_out: bool | None = False,
                 requested_at: datetime | None = None, **details: Any) -> None:
        super().__init__(code, message, **details)
        self.facts = facts or []
        self.carried_out = carried_out
        self.requested_at = requested_at or datetime.now(timezone.utc)


class GatewayOffline(GatewayError):
    """Nothing was sent, or what was sent was withdrawn before the gateway took it."""

    status = 503

    def __init__(self, message: str, gateway: str = "", facts: list | None = None, **details: Any) -> None:
        super().__init__("gateway_offline", message, facts, carried_out=False, **details)
        self.gateway = gateway


class GatewayNoAnswer(GatewayError):
    """The gateway took the command but gave no answer in time: whether it was carried out is
    not known here (the gateway's own audit record tells, once it reports)."""

    status = 504

    def __init__(self, message: str, gateway: str, facts: list | None = None, **details: Any) -> None:
        super().__init__("gateway_no_answer", message, facts, carried_out=None, **details)
        self.gateway = gateway
        self.details["carried_out"] = None  # the answer says it: not known


def _target(arguments: dict) -> str | None:
    """The robot a command is for, as the refusal names it."""
    run = arguments.get("run")
    robot = arguments.get("robot") or (run.get("robot") if isinstance(run, dict) else None)
    return str(robot) if robot else None


def _service_timeout(timeout: float | None) -> float:
    config = settings.LIFECYCLE
    try:
        service_timeout = float(timeout if timeout is not None else config["SERVICE_TIMEOUT"])
    except OverflowError:  # a whole number beyond a double: as long as we allow
        service_timeout = MAX_SERVICE_TIMEOUT
    if not math.isfinite(service_timeout):
        service_timeout = config["SERVICE_TIMEOUT"]
    return min(max(service_timeout, 0.1), MAX_SERVICE_TIMEOUT)


def call_gateway(gateway: str, command: str, timeout: float | None = None, **arguments: Any) -> dict:
    """Send ``command`` to the gateway named ``gateway`` and return its reply (``ok`` is True).

    ``timeout`` is the gateway's own bound on the ROS call; the site waits that long plus a
    grace period. Raises GatewayOffline when that gateway is not online (its heartbeat) or the
    command was withdrawn unanswered (not carried out), GatewayNoAnswer when the gateway took
    it and did not answer in time, and GatewayError with the gateway's code for a failed reply.
    """
    robot = _target(arguments)
    state = gateways.status(gateway)
    if not state.online:
        raise GatewayOffline(state.refusal(robot), gateway, english=in_english(state.refusal, robot))
    service_timeout = _service_timeout(timeout)
    wait = protocol.CALLS_PER_COMMAND * service_timeout + settings.LIFECYCLE["COMMAND_GRACE"]
    asked = datetime.now(timezone.utc)
    message = {
        "command": command,
        "request_id": uuid.uuid4().hex,
        "deadline": time.time() + wait,
        "requested_at": asked.isoformat(),
        "timeout": service_timeout,
        **arguments,
    }
    message.update(attribution.grants_for(message))  # audited commands: the site vouches for who asked
    call = _Call(gateway, message, robot, wait, asked)
    return call.run()


class _Call:
    """One command on its way: sent, awaited in slices, settled if unanswered."""

    def __init__(self, gateway: str, message: dict, robot: str | None, wait: float, asked: datetime) -> None:
        self.gateway, self.message, self.robot, self.wait, self.asked = gateway, message, robot, wait, asked
        self.encoded = protocol.encode(message)
        prefix = channel_prefix()
        self.queue = protocol.command_queue(prefix, gateway)
        self.reply_key = protocol.reply_key(prefix, gateway, message["request_id"])
        self.claim_key = protocol.claim_key(prefix, gateway, message["request_id"])
        self.client = gateways.redis_client()
        self.claim_seen: dict[str, float] = {}  # gateway instance that took the command -> first read (monotonic)

    def not_carried_out(self, reason: str, outcome: str = "rejected") -> list[dict]:
        return protocol.not_carried_out(self.gateway, self.message, reason, "site", outcome)

    def send(self) -> None:
        with self.client.pipeline() as pipe:
            pipe.lpush(self.queue, self.encoded)
            pipe.ltrim(self.queue, 0, protocol.COMMAND_QUEUE_LIMIT - 1)
            pipe.execute()

    def run(self) -> dict:
        try:
            try:
                self.send()
            except redis.ResponseError as exc:
                # Redis is full: a gateway beyond its quota, faster than the guard's count. Count
                # now (cutting it off), and send again once.
                if not redis_guard.is_out_of_memory(exc) or not redis_guard.relieve():
                    raise
                self.send()
        except redis.TimeoutError as exc:  # it may have been queued: the gateway's record will tell
            text, english = both(gettext_noop(
                "Redis, which links the site and gateway %(gateway)s, did not answer while the command was sent "
                "(%(error)s): whether it was carried out is not known. Check the node's state when Redis answers "
                "again."), gateway=self.gateway, error=exc)
            raise GatewayNoAnswer(text, self.gateway, requested_at=self.asked, english=english) from exc
        except redis.RedisError as exc:
            if self.robot:
                text, english = both(gettext_noop(
                    "Redis, which links the site and gateway %(gateway)s, is unreachable: %(error)s; nothing was "
                    "sent to %(robot)s."), gateway=self.gateway, error=exc, robot=self.robot)
            else:
                text, english = both(gettext_noop(
                    "Redis, which links the site and gateway %(gateway)s, is unreachable: %(error)s; nothing was "
                    "sent."), gateway=self.gateway, error=exc)
            raise GatewayOffline(text, self.gateway, self.not_carried_out(english), requested_at=self.asked,
                                 english=english) from exc
        end = time.monotonic() + self.wait
        trouble: Exception | None = None
        while (left := end - time.monotonic()) > 0:
            try:
                popped = self.client.blpop([self.reply_key], timeout=max(0.01, min(WAIT_SLICE_S, left)))
            except redis.RedisError as exc:  # Redis restarting or hanging: try again until the end
                trouble = exc
                time.sleep(min(0.5, max(0.0, end - time.monotonic())))
                continue
            trouble = None
            if popped is not None:
                return self.result(popped[1])
            if self.taker_gone():
                break  # whatever it took on, it will never answer
        return self.settle(trouble)

    def taker_gone(self) -> bool:
        """Whether the gateway process that took this command has ended (none took it: False)."""
        try:
            holder = self.client.get(self.claim_key)
        except redis.RedisError:
            return False
        instance = _instance(holder)
        if not instance:
            return False
        seen = self.claim_seen.setdefault(instance, time.monotonic())  # it had its connection then
        return presence.process_gone(self.client, protocol.client_name(self.gateway, instance), seen)

    def settle(self, trouble: Exception | None) -> dict:
        """No reply in time: withdraw the command if the gateway has not taken it; else say what
        is known. Returns the reply if it came meanwhile."""
        waited = {"gateway": self.gateway, "seconds": f"{self.wait:.0f}"}
        try:
            if self.client.set(self.claim_key, protocol.ABANDONED, nx=True, ex=protocol.CLAIM_TTL_S):
                self.client.lrem(self.queue, 1, self.encoded)
                if self.robot:
                    text, english = both(gettext_noop(
                        "Gateway %(gateway)s did not answer within %(seconds)s s, so the command was withdrawn: it "
                        "was not carried out, nothing was sent to %(robot)s."), **waited, robot=self.robot)
                else:
                    text, english = both(gettext_noop(
                        "Gateway %(gateway)s did not answer within %(seconds)s s, so the command was withdrawn: it "
                        "was not carried out, nothing was sent."), **waited)
                withdrawn = GatewayOffline(text, self.gateway, self.not_carried_out(english), requested_at=self.asked,
                                           english=english)
                withdrawn.details["carried_out"] = False
                raise withdrawn
            holder = self.client.get(self.claim_key)
            read = self.claim_seen.setdefault(_instance(holder), time.monotonic())
            popped = self.client.lpop(self.reply_key)
        except redis.RedisError as exc:
            trouble = exc
        else:
            if popped is not None:
                return self.result(popped)
            instance = _instance(holder)
            if instance and presence.process_gone(self.client, protocol.client_name(self.gateway, instance), read):
                if self.robot:
                    text, english = both(gettext_noop(
                        "Gateway %(gateway)s took the command, but its process ended before it answered: whether "
                        "it reached %(robot)s is not known. Check the node's state before you try again."),
                        gateway=self.gateway, robot=self.robot)
                else:
                    text, english = both(gettext_noop(
                        "Gateway %(gateway)s took the command, but its process ended before it answered: whether "
                        "it reached the robot is not known. Check the node's state before you try again."),
                        gateway=self.gateway)
                raise GatewayNoAnswer(text, self.gateway, self.not_carried_out(english, "timed_out"),
                                      requested_at=self.asked, english=english)
            text, english = both(gettext_noop(
                "Gateway %(gateway)s did not answer within %(seconds)s s. It had taken the command, so it may still "
                "be carried out; its outcome will be in the audit log when the gateway reports it. Check the "
                "node's state before you try again."), **waited)
            raise GatewayNoAnswer(text, self.gateway, requested_at=self.asked, english=english)
        # The gateway keeps what it did (or that it let the command expire) until Redis is back:
        # its record tells, so none is made here.
        if self.robot:
            text, english = both(gettext_noop(
                "Redis, which links the site and gateway %(gateway)s, stopped answering while the site waited for "
                "the gateway (%(error)s): whether the command for %(robot)s was carried out is not known; the audit "
                "log will show it when Redis is back. Check the node's state before you try again."),
                gateway=self.gateway, error=trouble, robot=self.robot)
        else:
            text, english = both(gettext_noop(
                "Redis, which links the site and gateway %(gateway)s, stopped answering while the site waited for "
                "the gateway (%(error)s): whether the command for the robot was carried out is not known; the audit "
                "log will show it when Redis is back. Check the node's state before you try again."),
                gateway=self.gateway, error=trouble)
        raise GatewayNoAnswer(text, self.gateway, requested_at=self.asked, english=english)

    def result(self, raw: bytes) -> dict:
        """The gateway's reply, if it is one the site can read: a JSON object of bounded size;
        a failure's code and message checked (gateway_input.failure), nothing else of it taken."""
        try:
            reply = json.loads(raw) if len(raw) <= MAX_REPLY_BYTES else None
        except (ValueError, RecursionError):  # (JSON nested deeper than Python's stack)
            reply = None
        if not isinstance(reply, dict):
            text, english = both(gettext_noop(
                "Gateway %(gateway)s answered with something the site cannot read (%(size)s bytes); check the "
                "node's state before you try again."), gateway=self.gateway, size=f"{len(raw):,}")
            raise GatewayError("gateway_error", text, carried_out=None, requested_at=self.asked, english=english)
        facts = reply.get("facts") if isinstance(reply.get("facts"), list) else []
        if reply.get("ok") is not True:
            code, message = checks.failure(reply)
            # (the gateway's own message is in its words, English: shown and stored as it is)
            text, english = (message, message) if message else both(
                gettext_noop("Gateway %(gateway)s reported an error."), gateway=self.gateway)
            raise GatewayError(
                code, text, facts,
                # A refusal means nothing reached the node; the gateway's own failure may come midway.
                carried_out=None if code == "gateway_error" else False,
                requested_at=self.asked, english=english,
            )
        return {**reply, "facts": facts}


def _instance(holder: bytes | str | None) -> str:
    """The gateway instance a claim names ("" for none, or the site's ABANDONED)."""
    if not holder:
        return ""
    text = holder.decode() if isinstance(holder, bytes) else holder
    try:
        value = json.loads(text)
    except ValueError:
        return ""
    return str(value.get("instance") or "") if isinstance(value, dict) else ""
