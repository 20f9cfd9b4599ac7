"""The site's side of talking to a gateway: one command on that gateway's queue, one reply,
a bounded wait. A gateway that is offline is not asked at all (GatewayOffline, at once)."""
from __future__ import annotations

import json
import math
import time
import uuid
from typing import Any

import redis
from django.conf import settings

from lifecycle_site.fleet import gateways
from lifecycle_site.fleet.gateways import MAX_SERVICE_TIMEOUT, channel_prefix
from ros_gateway.shared import protocol

__all__ = ["GatewayError", "GatewayOffline", "call_gateway", "channel_prefix", "MAX_SERVICE_TIMEOUT"]


class GatewayError(Exception):
    """A command could not be carried out; ``code`` and ``message`` are shown to the user.

    ``facts`` are what the gateway reported along with its refusal (an audit record of the
    attempt, say): the caller applies them like those of a successful reply."""

    status = 502

    def __init__(self, code: str, message: str, facts: list | None = None, **details: Any) -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.facts = facts or []
        self.details = details


class GatewayOffline(GatewayError):
    status = 503

    def __init__(self, message: str, gateway: str = "") -> None:
        super().__init__("gateway_offline", message)
        self.gateway = gateway


def _target(arguments: dict) -> str | None:
    """The robot a command is for, as the refusal names it."""
    run = arguments.get("run")
    robot = arguments.get("robot") or (run.get("robot") if isinstance(run, dict) else None)
    return str(robot) if robot else None


def call_gateway(gateway: str, command: str, timeout: float | None = None, **arguments: Any) -> dict:
    """Send ``command`` to the gateway named ``gateway`` and return its reply (``ok`` is True).

    ``timeout`` is the gateway's own bound on the ROS call; the site waits that long plus a
    grace period. Raises GatewayOffline when that gateway is not online (its heartbeat) or does
    not answer in time, and GatewayError with the gateway's code for any failed reply.
    """
    config = settings.LIFECYCLE
    robot = _target(arguments)
    state = gateways.status(gateway)
    if not state.online:
        raise GatewayOffline(state.refusal(robot), gateway)
    try:
        service_timeout = float(timeout if timeout is not None else config["SERVICE_TIMEOUT"])
    except OverflowError:  # a whole number beyond a double: as long as we allow
        service_timeout = MAX_SERVICE_TIMEOUT
    if not math.isfinite(service_timeout):
        service_timeout = config["SERVICE_TIMEOUT"]
    service_timeout = min(max(service_timeout, 0.1), MAX_SERVICE_TIMEOUT)
    # A transition makes up to three calls in a row: read the state, change it, re-read it.
    wait = 3 * service_timeout + config["COMMAND_GRACE"]
    request_id = uuid.uuid4().hex
    message = {
        "command": command,
        "request_id": request_id,
        "deadline": time.time() + wait,
        "timeout": service_timeout,
        **arguments,
    }
    prefix = channel_prefix()
    queue = protocol.command_queue(prefix, gateway)
    try:
        client = gateways.redis_client()
        with client.pipeline() as pipe:
            pipe.lpush(queue, protocol.encode(message))
            pipe.ltrim(queue, 0, protocol.COMMAND_QUEUE_LIMIT - 1)
            pipe.execute()
        popped = client.blpop([protocol.reply_key(prefix, gateway, request_id)], timeout=wait)
    except redis.RedisError as exc:
        raise GatewayOffline(
            f"Redis, which links the site and gateway {gateway}, is unreachable: {exc}", gateway
        ) from exc
    if popped is None:
        raise GatewayOffline(
            f"Gateway {gateway} did not answer within {wait:.0f} s"
            + (f"; the command for {robot} may still be carried out." if robot else "."),
            gateway,
        )
    reply = json.loads(popped[1])
    if not reply.get("ok"):
        error = reply.get("error") or {}
        raise GatewayError(
            error.get("code", "gateway_error"),
            error.get("message", f"Gateway {gateway} reported an error."),
            reply.get("facts"),
            **{k: v for k, v in reply.items() if k not in ("ok", "error", "request_id", "facts")},
        )
    return reply
