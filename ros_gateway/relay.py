"""The gateway's only link to the site: Redis, with this gateway's own keys and credentials.

Commands in and replies out (lists), the heartbeat and the lease (strings), the robots to
watch (the config key the site writes), facts out (streams, through outbox.py) and live
updates to browsers (Channels groups). Redis being down is survived: calls fail, are logged
at most once per ``quiet`` seconds, and work resumes when it is back.
"""
from __future__ import annotations

import asyncio
import json
import logging
import time

import redis.asyncio as aioredis
from channels.layers import get_channel_layer
from redis.asyncio.retry import Retry
from redis.backoff import ExponentialBackoff
from redis.exceptions import ConnectionError, TimeoutError

from ros_gateway import lease
from ros_gateway.shared import protocol

log = logging.getLogger(__name__)

# Longest a blocking read of the command queue waits; the socket timeout must outlast it.
COMMAND_WAIT_S = 1.0


def redis_client(url: str, client_name: str | None = None) -> aioredis.Redis:
    return aioredis.Redis.from_url(
        url,
        socket_connect_timeout=2,
        socket_timeout=10,
        # After a Redis restart the pooled connections are dead: retry on a fresh one.
        retry_on_error=[ConnectionError, TimeoutError],
        retry=Retry(ExponentialBackoff(cap=0.5, base=0.05), 3),
        health_check_interval=15,
        # Every connection bears this process's name: when they close, the site knows it ended.
        client_name=client_name,
    )


def safe_url(url: str) -> str:
    """The Redis URL without its password, for messages."""
    head, sep, tail = url.partition("@")
    if not sep:
        return url
    scheme, _, credentials = head.partition("://")
    user = credentials.split(":", 1)[0]
    return f"{scheme}://{user + ':***' if user else '***'}@{tail}"


# Compare-and-delete: a lease is removed only while it still names the holder that was checked.
DELETE_IF = "if redis.call('get', KEYS[1]) == ARGV[1] then return redis.call('del', KEYS[1]) end return 0"


PUBLISH_CONCURRENCY = 20  # messages; each goes to a few groups (node, robot, fleet)


class Relay:
    def __init__(self, gateway: str, redis_url: str, prefix: str, quiet: float = 30.0, instance: str = "") -> None:
        self.gateway = gateway
        self.prefix = prefix
        self.instance = instance or protocol.new_id()
        self.client_name = protocol.client_name(gateway, self.instance)
        self.url = safe_url(redis_url)
        self.redis = redis_client(redis_url, self.client_name)
        self.layer = get_channel_layer()
        self._quiet = quiet
        self._last_complaint = 0.0
        self.published = 0
        self.publish_failures = 0
        # Updates sent at once: a burst (discovery of a whole robot) beyond the channel layer's
        # Redis pool of 100 connections failed with "Too many connections" and was lost.
        self._publishing = asyncio.Semaphore(PUBLISH_CONCURRENCY)

    def key(self, what: str) -> str:
        return protocol.gateway_key(self.prefix, self.gateway, what)

    def complain(self, what: str, exc: Exception) -> None:
        now = time.monotonic()
        if now - self._last_complaint > self._quiet:
            self._last_complaint = now
            log.warning("%s failed (Redis at %s): %s", what, self.url, exc)

    # -- live updates -----------------------------------------------------------------
    async def publish(self, groups: list[str], message: dict) -> None:
        """Send ``message`` to the groups (together: one round trip's wait, not one per group);
        a failure is counted, never raised."""
        async with self._publishing:
            results = await asyncio.gather(*(self.layer.group_send(g, message) for g in groups),
                                           return_exceptions=True)
        for result in results:
            if isinstance(result, Exception):  # Redis down, message too large: the gateway goes on
                self.publish_failures += 1
                self.complain("publishing an update", result)
            else:
                self.published += 1

    # -- commands -----------------------------------------------------------------------
    async def next_command(self, wait: float = COMMAND_WAIT_S) -> dict | None:
        """The next command for this gateway, or None after ``wait`` seconds or on bad input."""
        try:
            popped = await self.redis.brpop([self.key("commands")], timeout=wait)
        except Exception as exc:
            self.complain("reading commands", exc)
            await asyncio.sleep(min(wait, 1.0))
            return None
        if popped is None:
            return None
        try:
            command = json.loads(popped[1])
            if not isinstance(command, dict) or not isinstance(command.get("request_id"), str):
                raise ValueError("not a command object")
            return command
        except ValueError as exc:
            log.warning("ignored a malformed command: %s", exc)
            return None

    def reply_parts(self, request_id: str, payload: dict) -> tuple[str, str]:
        """The key a reply goes to, and the reply as sent."""
        return protocol.reply_key(self.prefix, self.gateway, request_id), protocol.encode({"request_id": request_id,
                                                                                           **payload})

    async def reply(self, request_id: str, payload: dict) -> None:
        """Hand the reply over; tried a few times, since the site is waiting for it."""
        key, message = self.reply_parts(request_id, payload)
        for attempt in range(3):
            try:
                async with self.redis.pipeline(transaction=True) as pipe:
                    pipe.lpush(key, message)
                    pipe.expire(key, protocol.REPLY_TTL_S)
                    await pipe.execute()
                return
            except Exception as exc:
                if attempt == 2:
                    log.error("could not reply to request %s (Redis at %s): %s", request_id, self.url, exc)
                await asyncio.sleep(0.2 * (attempt + 1))

    # -- configuration, heartbeat, lease ----------------------------------------------
    async def read_config(self) -> dict | None:
        """The site's description of this gateway's robots, or None if there is none (yet)
        or Redis cannot be read (the caller keeps what it has)."""
        try:
            raw = await self.redis.get(self.key("config"))
        except Exception as exc:
            self.complain("reading the robots to watch", exc)
            return None
        if raw is None:
            return None
        try:
            config = json.loads(raw)
            if not isinstance(config, dict) or not isinstance(config.get("robots"), list):
                raise ValueError("no robot list")
            return config
        except ValueError as exc:
            log.warning("ignored the site's configuration for this gateway: %s", exc)
            return None

    async def read_verdict(self, run_id: str) -> bytes | None:
        """The site's verdict on a run (None while it has none); raises when Redis cannot be
        read. Only ever read: the site writes it (protocol.verdict_key)."""
        return await self.redis.get(protocol.verdict_key(self.prefix, self.gateway, run_id))

    async def beat(self, beat: dict) -> None:
        try:
            await self.redis.set(self.key("beat"), protocol.encode(beat))
        except Exception as exc:
            self.complain("writing the heartbeat", exc)

    async def take_lease(self, instance: str, ttl: float) -> str | None:
        """Hold this gateway's lease for ``ttl`` seconds; returns None when held, else the
        holder's description (another live instance of the same gateway). A holder that is
        provably dead (lease.py) is replaced at once rather than waited out."""
        key = self.key("lease")
        mine = json.dumps(lease.identity(instance))
        for _ in range(3):
            if await self.redis.set(key, mine, nx=True, px=int(ttl * 1000)):
                return None
            current = await self.redis.get(key)
            if current is None:  # it ran out between SET NX and GET: nobody holds it, try again
                continue
            holder = _parse(current)
            if holder.get("instance") == instance:
                await self.redis.pexpire(key, int(ttl * 1000))
                return None
            if not (current is not None and lease.provably_dead(holder)):
                break
            if await self.redis.eval(DELETE_IF, 1, key, current):
                log.info("took over gateway %r from instance %s: its process %s on this host has ended", self.gateway,
                         holder.get("instance"), holder.get("pid"))
        if current is None:
            return "nobody (it was released meanwhile)"
        return current.decode() if isinstance(current, bytes) else current

    async def claim(self, request_id: str) -> str | None:
        """Take a command before carrying it out. Returns "" when this instance has it now,
        else who has: protocol.ABANDONED when the site gave up on it, or another holder; None
        when Redis could not be asked (then it is not carried out: nobody would learn how it went)."""
        key = protocol.claim_key(self.prefix, self.gateway, request_id)
        mine = json.dumps({"instance": self.instance, "at": time.time()})
        try:
            if await self.redis.set(key, mine, nx=True, ex=protocol.CLAIM_TTL_S):
                return ""
            holder = await self.redis.get(key)
        except Exception as exc:
            self.complain("claiming a command", exc)
            return None
        return (holder.decode() if isinstance(holder, bytes) else holder) or "someone (it expired meanwhile)"

    async def renew_lease(self, instance: str, ttl: float) -> bool:
        """Extend the lease; False if another instance holds it now (this one was frozen or
        cut off for longer than its lease)."""
        try:
            return await self.take_lease(instance, ttl) is None
        except Exception as exc:
            self.complain("renewing the lease", exc)
            return True  # Redis unreachable: nobody else can take it over meanwhile either

    async def release_lease(self, instance: str) -> None:
        try:
            current = await self.redis.get(self.key("lease"))
            if current is not None and _parse(current).get("instance") == instance:
                await self.redis.eval(DELETE_IF, 1, self.key("lease"), current)
        except Exception:
            pass

    async def close(self) -> None:
        try:
            await self.redis.aclose()
        except Exception:
            pass


def _parse(raw: bytes | str | None) -> dict:
    """A lease's holder (an older gateway wrote only its instance; anything else: {})."""
    try:
        value = json.loads(raw) if raw is not None else {}
    except ValueError:
        return {}
    return value if isinstance(value, dict) else {}
