"""The gateway's only link to the site: Redis, with this gateway's own keys and credentials.

Commands in and replies out (lists), the heartbeat and the lease (strings), the robots to
watch (the config key the site writes), facts out (streams, through outbox.py) and live
updates for open pages (the ``live`` stream, which the site checks and sends on). Redis being
down is survived: calls fail, are logged at most once per ``quiet`` seconds, and work resumes
when it is back.

The gateway's Redis user may run only what is needed here (lifecycle_site/gateway_link/redis_users.py):
no scripts, so the lease's compare-and-delete is a WATCH/MULTI transaction.
"""
from __future__ import annotations

import asyncio
import json
import logging
import time

import redis.asyncio as aioredis
from redis.asyncio.retry import Retry
from redis.backoff import ExponentialBackoff
from redis.exceptions import ConnectionError, TimeoutError, WatchError

from ros_gateway import lease
from ros_gateway.budget import StreamBudget
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




class Relay:
    def __init__(self, gateway: str, redis_url: str, prefix: str, quiet: float = 30.0, instance: str = "") -> None:
        self.gateway = gateway
        self.prefix = prefix
        self.instance = instance or protocol.new_id()
        self.client_name = protocol.client_name(gateway, self.instance)
        self.url = safe_url(redis_url)
        self.redis = redis_client(redis_url, self.client_name)
        self._quiet = quiet
        self._last_complaint = 0.0
        self.published = 0
        self.publish_failures = 0
        self.live = StreamBudget(protocol.STREAM_SHARES["live"], protocol.LIVE_MAXLEN)

    def key(self, what: str) -> str:
        return protocol.gateway_key(self.prefix, self.gateway, what)

    def complain(self, what: str, exc: Exception) -> None:
        now = time.monotonic()
        if now - self._last_complaint > self._quiet:
            self._last_complaint = now
            log.warning("%s failed (Redis at %s): %s", what, self.url, exc)

    # -- live updates -----------------------------------------------------------------
    async def publish(self, message: dict) -> None:
        """Hand a live update to the site (its ``live`` stream; the site checks it and sends it
        to the pages that show what it is about); a failure is counted, never raised."""
        body = protocol.encode(message)
        if len(body) > protocol.MAX_LIVE_BYTES:  # the site would not read it (and quarantine us)
            self.publish_failures += 1
            log.warning("a live update of %d bytes was not sent (at most %d)", len(body), protocol.MAX_LIVE_BYTES)
            return
        try:
            await self.redis.xadd(self.key("live"), {"m": body}, maxlen=self.live.add(len(body)), approximate=False)
            self.published += 1
        except Exception as exc:  # Redis down: the gateway goes on, the pages catch up on reload
            self.publish_failures += 1
            self.complain("publishing an update", exc)

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
            if await self._delete_if(key, current):
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
                await self._delete_if(self.key("lease"), current)
        except Exception:
            pass

    async def _delete_if(self, key: str, expected: bytes) -> bool:
        """Delete ``key`` only while it still holds ``expected`` (a lease that was checked)."""
        async with self.redis.pipeline(transaction=True) as pipe:
            try:
                await pipe.watch(key)
                if await pipe.get(key) != expected:
                    return False
                pipe.multi()
                pipe.delete(key)
                return bool((await pipe.execute())[0])
            except WatchError:  # it changed meanwhile: someone else holds it now
                return False

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
