"""Several ingest processes side by side: who reads which gateway's streams, and who does the
site-wide work.

Each gateway's streams (facts, logs, live) are read by one ingest process at a time, which holds
that gateway's lease (``{prefix}:site:ingest:gw:NAME``), so that its facts are applied in order.
The processes running (``{prefix}:site:ingest:members``, a sorted set of their last turns) share
the gateways fairly: each takes free gateways up to its fair share and gives back what is beyond
it, so a second process started beside a busy one takes half of the work within seconds, and a
process that stops (or freezes) has its gateways taken over when their leases run out.

One of them also holds the site's lease (protocol.ingest_lease_key) and does the work that must
happen once per site: alert rules, configs, Redis users, pruning. The others hand it what the
alert rules need from the facts they stored (a bounded list in Redis).
"""
from __future__ import annotations

import json
import math
import time
from datetime import datetime

import redis

from lifecycle_site.ingest.observations import Observation
from ros_gateway.shared import protocol

LEASE_S = 15.0
MEMBER_S = 15.0  # a process whose last turn is older than this is not counted
OBSERVATIONS_KEPT = 10_000

RENEW = "if redis.call('get', KEYS[1]) == ARGV[1] then return redis.call('pexpire', KEYS[1], ARGV[2]) end return 0"
RELEASE = "if redis.call('get', KEYS[1]) == ARGV[1] then return redis.call('del', KEYS[1]) end return 0"


def gateway_lease_key(prefix: str, gateway: str) -> str:
    return f"{prefix}:site:ingest:gw:{gateway}"


def members_key(prefix: str) -> str:
    return f"{prefix}:site:ingest:members"


def observations_key(prefix: str) -> str:
    return f"{prefix}:site:ingest:observed"


class Shares:
    """This process's gateways and its part in the site-wide work."""

    def __init__(self, client: redis.Redis, prefix: str, me: str) -> None:
        self.redis, self.prefix, self.me = client, prefix, me
        self.held: set[str] = set()
        self.leader = False

    # --- who is running --------------------------------------------------------------------

    def report_turn(self, detail: dict) -> int:
        """Record that this process finished a turn (``detail``: what /readyz may show); returns
        how many processes have done so within MEMBER_S."""
        now = time.time()
        key = members_key(self.prefix)
        with self.redis.pipeline(transaction=False) as pipe:
            pipe.zadd(key, {self.me: now})
            pipe.zremrangebyscore(key, "-inf", now - 10 * MEMBER_S)  # long gone: forget them
            pipe.zcount(key, now - MEMBER_S, "+inf")
            pipe.hset(f"{key}:detail", self.me, json.dumps({**detail, "at": now}))
            pipe.expire(f"{key}:detail", int(10 * MEMBER_S))
            return max(1, int(pipe.execute()[2]))

    def leave(self) -> None:
        """Give back every lease and leave the members (a clean stop)."""
        for name in list(self.held):
            self.redis.eval(RELEASE, 1, gateway_lease_key(self.prefix, name), self.me)
        self.held.clear()
        if self.leader:
            self.redis.eval(RELEASE, 1, protocol.ingest_lease_key(self.prefix), self.me)
            self.leader = False
        self.redis.zrem(members_key(self.prefix), self.me)
        self.redis.hdel(f"{members_key(self.prefix)}:detail", self.me)

    # --- the site-wide lease -----------------------------------------------------------------

    def hold_site_lease(self) -> bool:
        key, ms = protocol.ingest_lease_key(self.prefix), int(LEASE_S * 1000)
        self.leader = bool(self.redis.set(key, self.me, nx=True, px=ms)) or bool(
            self.redis.eval(RENEW, 1, key, self.me, ms))
        return self.leader

    # --- the gateways' leases ----------------------------------------------------------------

    def rebalance(self, gateways: list[str], members: int) -> set[str]:
        """Keep, take and give back gateways' leases so that this process holds its fair share
        of ``gateways``; returns the gateways it holds now."""
        ms = int(LEASE_S * 1000)
        wanted = set(gateways)
        for name in list(self.held):
            key = gateway_lease_key(self.prefix, name)
            if name not in wanted:
                self.redis.eval(RELEASE, 1, key, self.me)
                self.held.discard(name)
            elif not self.redis.eval(RENEW, 1, key, self.me, ms):
                self.held.discard(name)  # it ran out (this process was frozen) and was taken over
        fair = math.ceil(len(wanted) / max(members, 1))
        for name in sorted(self.held)[fair:]:  # beyond the fair share: for a newcomer to take
            self.redis.eval(RELEASE, 1, gateway_lease_key(self.prefix, name), self.me)
            self.held.discard(name)
        for name in sorted(wanted - self.held):
            if len(self.held) >= fair:
                break
            if self.redis.set(gateway_lease_key(self.prefix, name), self.me, nx=True, px=ms):
                self.held.add(name)
        return set(self.held)

    # --- what the alert rules need ------------------------------------------------------------

    def hand_over(self, seen: list[Observation]) -> None:
        """Observations of facts this process stored, for the process that evaluates the rules."""
        if not seen:
            return
        key = observations_key(self.prefix)
        with self.redis.pipeline(transaction=False) as pipe:
            pipe.rpush(key, *(json.dumps({**o.__dict__, "at": o.at.isoformat()}) for o in seen))
            pipe.ltrim(key, -OBSERVATIONS_KEPT, -1)
            pipe.execute()

    def take_over(self) -> list[Observation]:
        """What the other processes handed over (the leader's side)."""
        key = observations_key(self.prefix)
        with self.redis.pipeline(transaction=True) as pipe:
            pipe.lrange(key, 0, -1)
            pipe.delete(key)
            raw = pipe.execute()[0]
        found = []
        for item in raw:
            try:
                data = json.loads(item)
                found.append(Observation(**{**data, "at": datetime.fromisoformat(data["at"])}))
            except (ValueError, TypeError, KeyError):
                continue
        return found


def turns(client: redis.Redis, prefix: str) -> list[dict]:
    """Every ingest process's last turn, newest first: {"me", "at" (epoch), ...detail}."""
    detail = client.hgetall(f"{members_key(prefix)}:detail")
    found = []
    for me, raw in detail.items():
        try:
            data = json.loads(raw)
        except ValueError:
            continue
        if isinstance(data, dict) and isinstance(data.get("at"), (int, float)):
            found.append({**data, "me": me.decode() if isinstance(me, bytes) else me})
    return sorted(found, key=lambda d: -d["at"])
