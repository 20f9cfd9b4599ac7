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

from ros_gateway import protocol

log = logging.getLogger(__name__)


class Relay:
    def __init__(self, quiet: float = 30.0) -> None:
        self.prefix = settings.CHANNEL_LAYERS["default"]["CONFIG"].get("prefix", "lifecycle")
        self.layer = get_channel_layer()
        self.redis = aioredis.Redis.from_url(settings.REDIS_URL, socket_connect_timeout=2, socket_timeout=10)
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
        """Send ``message`` to each group; a failure is counted, never raised."""
        for group in groups:
            try:
                await self.layer.group_send(group, message)
                self.published += 1
            except Exception as exc:  # Redis down, message too large: the gateway goes on
                self.publish_failures += 1
                self._complain("publishing an update", exc)

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
        key = protocol.reply_key(self.prefix, request_id)
        try:
            async with self.redis.pipeline(transaction=True) as pipe:
                pipe.lpush(key, json.dumps({"request_id": request_id, **payload}))
                pipe.expire(key, protocol.REPLY_TTL_S)
                await pipe.execute()
        except Exception as exc:
            self._complain("replying to the site", exc)

    async def close(self) -> None:
        try:
            await self.redis.aclose()
        except Exception:
            pass
