"""The site's side of talking to the ROS gateway: one command, one reply, a bounded wait."""
from __future__ import annotations

import json
import math
import time
import uuid
from functools import lru_cache
from typing import Any

import redis
from django.conf import settings
from django.core.signals import setting_changed
from django.db.models.signals import post_delete, post_save
from redis.backoff import ExponentialBackoff
from redis.retry import Retry

from lifecycle_site.fleet.models import GatewayHeartbeat
from ros_gateway.shared import protocol


class GatewayError(Exception):
    """A command could not be carried out; ``code`` and ``message`` are shown to the user."""

    status = 502

    def __init__(self, code: str, message: str, **details: Any) -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.details = details


class GatewayOffline(GatewayError):
    status = 503

    def __init__(self, message: str) -> None:
        super().__init__("gateway_offline", message)


def channel_prefix() -> str:
    return settings.CHANNEL_LAYERS["default"]["CONFIG"].get("prefix", "lifecycle")


# Upper bound of a service timeout a caller may ask for, so every wait stays bounded.
MAX_SERVICE_TIMEOUT = 25.0


@lru_cache(maxsize=1)
def _redis() -> redis.Redis:
    # A Redis that is down must show as an error within seconds (connect timeout); the read
    # timeout only has to outlast the longest blocking wait for a reply.
    return redis.Redis.from_url(
        settings.REDIS_URL, socket_connect_timeout=2, socket_timeout=3 * MAX_SERVICE_TIMEOUT + 15,
        retry_on_error=[redis.ConnectionError, redis.TimeoutError],
        retry=Retry(ExponentialBackoff(cap=0.5, base=0.05), 2),
        health_check_interval=30,
    )


# How long a process trusts its last look at the gateway's heartbeat (a query of ~0.3 ms on
# every command otherwise). A gateway that stops cleanly deletes its heartbeat, so commands
# are refused with the clear "offline" error at most this long after it stopped.
ONLINE_CACHE_S = 1.0
_online: tuple[float, bool] | None = None  # (when it was read, time.monotonic(); the answer)


def gateway_online() -> bool:
    """``GatewayHeartbeat.online()``, read at most once per ONLINE_CACHE_S in this process."""
    global _online
    now = time.monotonic()
    seen = _online
    if seen is not None and 0 <= now - seen[0] < ONLINE_CACHE_S:
        return seen[1]
    online = GatewayHeartbeat.online()
    _online = (now, online)
    return online


def forget_gateway_status(**_) -> None:
    """Read the heartbeat afresh next time (a heartbeat written here, or settings changed)."""
    global _online
    _online = None


post_save.connect(forget_gateway_status, sender=GatewayHeartbeat, dispatch_uid="gateway_client.heartbeat_saved")
post_delete.connect(forget_gateway_status, sender=GatewayHeartbeat, dispatch_uid="gateway_client.heartbeat_deleted")
setting_changed.connect(forget_gateway_status, dispatch_uid="gateway_client.setting_changed")


def call_gateway(command: str, timeout: float | None = None, **arguments: Any) -> dict:
    """Send ``command`` to the gateway and return its reply (``ok`` is True).

    ``timeout`` is the gateway's own bound on the ROS call; the site waits that long plus a
    grace period. Raises GatewayOffline when no gateway is alive or it does not answer in
    time, and GatewayError with the gateway's code for any failed reply.
    """
    config = settings.LIFECYCLE
    if not gateway_online():
        raise GatewayOffline(
            "The ROS gateway is offline (no heartbeat for "
            f"{config['GATEWAY_OFFLINE_AFTER']:.0f} s); nothing was sent to the robot."
        )
    service_timeout = float(timeout if timeout is not None else config["SERVICE_TIMEOUT"])
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
    queue = protocol.command_queue(prefix)
    try:
        client = _redis()
        with client.pipeline() as pipe:
            pipe.lpush(queue, json.dumps(message))
            pipe.ltrim(queue, 0, protocol.COMMAND_QUEUE_LIMIT - 1)
            pipe.execute()
        popped = client.blpop([protocol.reply_key(prefix, request_id)], timeout=wait)
    except redis.RedisError as exc:
        raise GatewayOffline(f"Redis, which links the site and the ROS gateway, is unreachable: {exc}") from exc
    if popped is None:
        raise GatewayOffline(f"The ROS gateway did not answer within {wait:.0f} s.")
    reply = json.loads(popped[1])
    if not reply.get("ok"):
        error = reply.get("error") or {}
        raise GatewayError(
            error.get("code", "gateway_error"),
            error.get("message", "The ROS gateway reported an error."),
            **{k: v for k, v in reply.items() if k not in ("ok", "error", "request_id")},
        )
    return reply
