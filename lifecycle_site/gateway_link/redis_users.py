"""The Redis user each gateway connects with: only its own keys and the channel layer's, only
the commands it needs; made by ``manage.py add_gateway``, re-made by the ingest process after a
Redis restart, dropped with the gateway."""
from __future__ import annotations

import hashlib
import logging

import redis
from django.db import transaction
from django.db.models.signals import post_delete

from lifecycle_site.fleet.models import Gateway
from lifecycle_site.gateway_link.gateways import channel_prefix, redis_client
from ros_gateway.shared import protocol

log = logging.getLogger(__name__)

# What a gateway may run (checked against Redis 7 by tests/unit/test_gateway_acl.py), each for
# one job: its command queue (BRPOP), replies (LPUSH, EXPIRE), claims, heartbeat, lease and
# config (SET, GET, PEXPIRE, DEL; the lease's compare-and-delete with WATCH/MULTI), its streams
# (XADD; XLEN and MEMORY USAGE to count what a predecessor left in them), and what a connection
# needs. No scripts (a script runs as long as it likes, blocking every other client of Redis, and
# cannot always be killed), no SELECT, no key listing, nothing of the Channels layer: its live
# updates go to its own stream, which the site checks.
GATEWAY_COMMANDS = [
    "-@all",
    "+ping", "+hello", "+auth", "+client|setname", "+client|getname", "+client|id", "+quit", "+reset",
    "+brpop", "+lpush", "+expire", "+pexpire", "+get", "+set", "+del", "+xadd", "+xlen", "+memory|usage",
    "+multi", "+exec", "+discard", "+watch", "+unwatch",
]


def password_sha256(password: str) -> str:
    return hashlib.sha256(password.encode()).hexdigest()


def _major_version(client: redis.Redis) -> int:
    try:
        return int(str(client.info("server").get("redis_version", "7")).split(".")[0])
    except (redis.RedisError, ValueError):
        return 7


def acl_rules(gateway: Gateway, prefix: str | None = None, redis_major: int = 7) -> list[str]:
    """The gateway's user: its password, exactly its own keys (those the site writes for it
    read-only, and its command queue only to take from: a selector that allows nothing but
    BRPOP there), no Pub/Sub channels, and GATEWAY_COMMANDS. Redis 6 has neither read-only keys
    nor selectors: there the site's keys are writable too (the Redis guard counts them)."""
    prefix = prefix or channel_prefix()
    writes, reads = protocol.gateway_key_patterns(prefix, gateway.name)
    state = "on" if gateway.quarantined is None else "off"
    if redis_major < 7:
        return ["reset", state, f"#{gateway.redis_password_sha256}", *(f"~{k}" for k in writes + reads),
                "resetchannels", *GATEWAY_COMMANDS]
    queue = protocol.command_queue(prefix, gateway.name)
    return ["reset", state, f"#{gateway.redis_password_sha256}", *(f"~{k}" for k in writes if k != queue),
            *(f"%R~{k}" for k in reads), "resetchannels", *GATEWAY_COMMANDS, f"(~{queue} -@all +brpop)"]


def apply_user(gateway: Gateway, client: redis.Redis | None = None) -> None:
    """Create or update the gateway's Redis user from the stored hash (no-op without one)."""
    if not gateway.redis_password_sha256:
        return
    client = client or redis_client()
    client.execute_command("ACL", "SETUSER", gateway.redis_user,
                           *acl_rules(gateway, redis_major=_major_version(client)))
    if gateway.quarantined is not None:  # "off" keeps open connections working: close them
        disconnect_user(gateway.name, client)


def user_is_current(gateway: Gateway, client: redis.Redis | None = None) -> bool:
    """Whether Redis has the gateway's user with the stored password, enabled exactly while the
    gateway is not quarantined (Redis may have restarted without its users)."""
    found = (client or redis_client()).acl_getuser(gateway.redis_user)
    if not found or list(found.get("passwords") or []) != [gateway.redis_password_sha256]:
        return False
    flags = [f.decode() if isinstance(f, bytes) else f for f in found.get("flags") or []]
    return ("on" in flags) == (gateway.quarantined is None)


def disconnect_user(gateway_name: str, client: redis.Redis | None = None) -> None:
    """Close the connections a gateway opened with its previous password."""
    try:
        (client or redis_client()).execute_command("CLIENT", "KILL", "USER", f"gw-{gateway_name}")
    except redis.ResponseError:
        pass  # no such user, or no connection of it


def delete_user(gateway_name: str, client: redis.Redis | None = None) -> None:
    client = client or redis_client()
    client.execute_command("ACL", "DELUSER", f"gw-{gateway_name}")
    disconnect_user(gateway_name, client)


def _gateway_deleted(sender, instance: Gateway, **kwargs) -> None:
    name = instance.name

    def drop() -> None:
        try:
            delete_user(name)
        except redis.RedisError as exc:
            log.warning("could not delete the Redis user of gateway %s: %s", name, exc)

    transaction.on_commit(drop)


post_delete.connect(_gateway_deleted, sender=Gateway, dispatch_uid="gateway_link.gateways.gateway_deleted")
