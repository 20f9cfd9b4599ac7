"""Cutting a gateway off, and letting it back in.

(Only gateways with a Redis user of their own, ``manage.py add_gateway``: one that uses the
site's own user is the site's, and is never cut off.)

A gateway is a stranger to the site (it runs on a plant-floor device, which may be stolen,
misconfigured or compromised). When what it holds or sends breaks the rules (its Redis keys over
their quota, a stream of the wrong type, an entry that is malformed or too large) the site
quarantines it: its Redis user is disabled and its connections closed, its streams are no longer
read, commands for its robots are refused with the reason, and the fleet page, the API,
``/metrics`` and the "gateway offline" alert rules say so. Nothing else is affected: the other
gateways go on.

Redis is told first (that is what protects the others, and it works with the database down);
the site keeps the quarantine in a hash of its own (``{prefix}:site:quarantined``, which no
gateway can reach), read with the heartbeats, and in the Gateway row, the record pages show. An
administrator lifts it in the admin (or by ``manage.py add_gateway NAME``, which also gives
the gateway a new password).
"""
from __future__ import annotations

import json
import logging
from datetime import datetime, timezone
from typing import Iterable

import redis
from django.db import DatabaseError
from django.db.models import F

from lifecycle_site.fleet.models import Gateway
from lifecycle_site.gateway_link import gateways, redis_users
from lifecycle_site.gateway_link.gateways import channel_prefix, parse_quarantine, quarantine_key, redis_client
from ros_gateway.shared import protocol

log = logging.getLogger(__name__)

REASON_LENGTH = 500


def quarantine(name: str, reason: str, client: redis.Redis | None = None, drop: Iterable[str] = ()) -> bool:
    """Cut gateway ``name`` off for ``reason`` (one sentence, for a person). ``drop``: which of
    its keys to delete (GATEWAY_WRITES entries, e.g. "facts", "reply:*"), to give Redis back
    the memory they hold or to remove a key of the wrong type. Returns True when this call
    quarantined it (False: it was already). Raises redis.RedisError when Redis cannot be told."""
    client = client or redis_client()
    prefix = channel_prefix()
    since = datetime.now(timezone.utc)
    reason = " ".join(reason.split())[:REASON_LENGTH]
    row = Gateway.objects.filter(name=name).only("name", "redis_password_sha256", "quarantined").first()
    if row is not None and not row.redis_password_sha256:
        # It connects with the site's own Redis user (the gateway ``local`` of make demo and the
        # central compose file): it is the site's, not a stranger, and cutting it off would cut
        # off the site's own robots. What broke the rule is deleted, and said loudly.
        dropped = drop_keys(name, drop, client)
        log.error("gateway %s (the site's own Redis user) broke a rule: %s; not cut off%s", name, reason,
                  f" (deleted its keys: {', '.join(dropped)})" if dropped else "")
        return False
    # In this order: with Redis full, writes are refused until the keys are deleted (ACL SETUSER,
    # CLIENT KILL and UNLINK are not), so the hash's entry comes last.
    if row is not None:
        row.quarantined = row.quarantined or since
        redis_users.apply_user(row, client)  # "off": it cannot log in again
        redis_users.disconnect_user(name, client)  # and what it has open is closed
    dropped = drop_keys(name, drop, client)
    entry = json.dumps({"since": since.isoformat(), "reason": reason})
    new = bool(client.hsetnx(quarantine_key(prefix), name, entry))
    try:
        Gateway.objects.filter(name=name, quarantined__isnull=True).update(
            quarantined=since, quarantine_reason=reason, quarantines=F("quarantines") + 1)
    except DatabaseError as exc:  # the hash holds it; keep_records() writes the row later
        log.warning("gateway %s quarantined, but its row could not be updated yet: %s", name, exc)
    gateways.forget_beats()
    if new:
        log.error("gateway %s quarantined: %s%s", name, reason,
                  f" (deleted its keys: {', '.join(dropped)})" if dropped else "")
    return new


def drop_keys(name: str, which: Iterable[str], client: redis.Redis) -> list[str]:
    """Delete these of the gateway's keys (a ``*`` entry by a scan of its own keys); returns
    the entries that had any."""
    prefix = channel_prefix()
    dropped = []
    for what in which:
        if what not in protocol.GATEWAY_WRITES:
            raise ValueError(f"{what!r} is not a key a gateway writes")
        pattern = protocol.gateway_key(prefix, name, what)
        keys = list(client.scan_iter(match=pattern, count=1000)) if "*" in what else [pattern]
        deleted = 0
        for start in range(0, len(keys), 500):
            deleted += client.unlink(*keys[start:start + 500])
        if deleted:
            dropped.append(what)
    return dropped


def lift(gateway: Gateway, client: redis.Redis | None = None) -> None:
    """Let a quarantined gateway work again (its user enabled; its streams read from where the
    site stopped). Its counters stay."""
    client = client or redis_client()
    lifted = Gateway(pk=gateway.pk, name=gateway.name, redis_password_sha256=gateway.redis_password_sha256)
    client.hdel(quarantine_key(), gateway.name)  # Redis first: if it does not answer, nothing is lifted
    redis_users.apply_user(lifted, client)
    Gateway.objects.filter(pk=gateway.pk).update(quarantined=None, quarantine_reason="")
    gateway.quarantined, gateway.quarantine_reason = None, ""
    gateways.forget_beats()
    log.warning("gateway %s: quarantine lifted", gateway.name)


def current(client: redis.Redis | None = None) -> dict[str, dict]:
    """Quarantined gateways as Redis holds them: name -> {"since": datetime | None, "reason": str}."""
    raw = (client or redis_client()).hgetall(quarantine_key())
    return {(k.decode() if isinstance(k, bytes) else k): parse_quarantine(v) or {} for k, v in raw.items()}


def keep_records(client: redis.Redis | None = None) -> None:
    """Make Redis and the database agree: a quarantine only Redis knows (the database was
    unavailable) goes into the row, one only the row knows (Redis restarted without its data)
    goes back into Redis, with the gateway's user disabled again."""
    client = client or redis_client()
    in_redis = current(client)
    rows = {g.name: g for g in Gateway.objects.filter(quarantined__isnull=False)}
    for name, entry in in_redis.items():
        if name not in rows:
            Gateway.objects.filter(name=name, quarantined__isnull=True).update(
                quarantined=entry["since"] or datetime.now(timezone.utc), quarantine_reason=entry["reason"],
                quarantines=F("quarantines") + 1)
    for name, row in rows.items():
        if name not in in_redis:
            client.hset(quarantine_key(), name, json.dumps({"since": row.quarantined.isoformat(),
                                                          "reason": row.quarantine_reason}))
