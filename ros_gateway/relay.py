"""The gateway's links to the site: commands in and replies out (Redis lists), live
updates out (Channels groups). Redis being down is survived: calls fail, are logged at
most once per ``quiet`` seconds, and work resumes when it is back."""
from __future__ import annotations

import asyncio
import json
import logging
import time

import redis.asyncio as aioredis
from channels.layers import get_channel_layer
from django.conf import settings
from redis.asyncio.retry import Retry
from redis.backoff import ExponentialBackoff
from redis.exceptions import ConnectionError, TimeoutError

from ros_gateway.shared import protocol

log = logging.getLogger(__name__)


class Relay:
    def __init__(self, quiet: float = 30.0) -> None:
        self.prefix = settings.CHANNEL_LAYERS["default"]["CONFIG"].get("prefix", "lifecycle")
        self.layer = get_channel_layer()
        self.redis = aioredis.Redis.from_url(
            settings.REDIS_URL,
            socket_connect_timeout=2,
            socket_timeout=10,
            # After a Redis restart the pooled connections are dead: retry on a fresh one.
            retry_on_error=[ConnectionError, TimeoutError],
            retry=Retry(ExponentialBackoff(cap=0.5, base=0.05), 3),
            health_check_interval=15,
        )
        self._quiet = quiet
        self._last_complaint = 0.0
        self.published = 0
        self.publish_failures = 0

    def _complain(self, what: str, exc: Exception) -> None:
        now = time.monotonic()
        if now - self._last_complaint > self._quiet:
            self._last_complaint = now
            log.warning("%s failed (Redis at %s): %s", what, settings.REDIS_URL, exc)

    async def publish(self, groups: list[str], message: dict) -> None:
        """Send ``message`` to the groups (together: one round trip's wait, not one per group);
        a failure is counted, never raised."""
        results = await asyncio.gather(*(self.layer.group_send(g, message) for g in groups), return_exceptions=True)
        for result in results:
            if isinstance(result, Exception):  # Redis down, message too large: the gateway goes on
                self.publish_failures += 1
                self._complain("publishing an update", result)
            else:
                self.published += 1

    async def next_command(self, wait: float = 1.0) -> dict | None:
        """The next command for the gateway, or None after ``wait`` seconds or on bad input."""
        try:
            popped = await self.redis.brpop([protocol.command_queue(self.prefix)], timeout=wait)
        except Exception as exc:
            self._complain("reading commands", exc)
            await asyncio.sleep(min(wait, 1.0))
            return None
        if popped is None:
            return None
        try:
            command = json.loads(popped[1])
            if not isinstance(command, dict) or "request_id" not in command:
                raise ValueError("not a command object")
            return command
        except ValueError as exc:
            log.warning("ignored a malformed command: %s", exc)
            return None

    async def reply(self, request_id: str, payload: dict) -> None:
        """Hand the reply over; tried a few times, since the site is waiting for it."""
        key = protocol.reply_key(self.prefix, request_id)
        message = json.dumps({"request_id": request_id, **payload})
        for attempt in range(3):
            try:
                async with self.redis.pipeline(transaction=True) as pipe:
                    pipe.lpush(key, message)
                    pipe.expire(key, protocol.REPLY_TTL_S)
                    await pipe.execute()
                return
            except Exception as exc:
                if attempt == 2:
                    log.error("could not reply to request %s (Redis at %s): %s", request_id, settings.REDIS_URL, exc)
                await asyncio.sleep(0.2 * (attempt + 1))

    async def close(self) -> None:
        try:
            await self.redis.aclose()
        except Exception:
            pass
