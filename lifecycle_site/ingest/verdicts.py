"""The site's final word on group runs, told to their gateway.

Whenever the site ends a run the gateway may still be carrying out (the gateway silent too
long, a restart, a start whose answer never came), it writes the verdict under the gateway's
own keys (``protocol.verdict_key``). The gateway reads it before a run's next step after a
pause and stops there: a verdict is final, and no node is driven for a run that is over.
"""
from __future__ import annotations

import logging
from datetime import datetime, timezone
from typing import Iterable

import redis

from lifecycle_site.gateway_link.gateways import channel_prefix, redis_client
from ros_gateway.shared import protocol

log = logging.getLogger(__name__)


def publish(gateway: str, run_ids: Iterable[str], status: str, message: str, at: datetime | None = None,
            client: redis.Redis | None = None) -> bool:
    """Write the verdict of each run (one round trip); False if Redis could not take it (logged:
    a gateway that cannot read Redis either does not take a run's next step)."""
    run_ids = list(run_ids)
    if not run_ids:
        return True
    prefix = channel_prefix()
    value = protocol.encode({"status": status, "message": message,
                             "at": (at or datetime.now(timezone.utc)).isoformat()})
    try:
        with (client or redis_client()).pipeline(transaction=False) as pipe:
            for run_id in run_ids:
                pipe.set(protocol.verdict_key(prefix, gateway, run_id), value, ex=protocol.VERDICT_TTL_S)
            pipe.execute()
    except redis.RedisError as exc:
        log.error("could not tell gateway %s that %d run(s) ended %s (Redis: %s)", gateway, len(run_ids), status, exc)
        return False
    return True
