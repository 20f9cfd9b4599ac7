"""The Redis user each gateway connects with: only its own keys and the channel layer's, only
the commands it needs; made by ``manage.py add_gateway``, re-made by the ingest process after a
Redis restart, dropped with the gateway."""
from __future__ import annotations

import hashlib
import logging

import redis
from django.db import transaction
from django.db.models.signals import post_delete

from lifecycle_site.fleet.gateways import channel_prefix, redis_client
from lifecycle_site.fleet.models import Gateway
from ros_gateway.shared import protocol

log = logging.getLogger(__name__)

# What a gateway may run (checked against Redis 7 by tests/unit/test_gateway_acl.py):
# its command queue and replies (BRPOP, LPUSH, EXPIRE), its streams (XADD), its heartbeat,
# lease and config (SET, GET; DEL and EVAL for the lease), and what channels-redis runs to
# send to a group (ZREMRANGEBYSCORE, ZRANGE, EVAL of ZCOUNT/ZADD/EXPIRE). Keys: its own and
# the channel layer's.
GATEWAY_COMMANDS = [
    "-@all", "+@connection", "-@dangerous",
    "+brpop", "+lpush", "+expire", "+pexpire", "+get", "+set", "+del", "+xadd",
    "+zremrangebyscore", "+zrange", "+zcount", "+zadd",
    "+eval", "+evalsha", "+multi", "+exec", "+discard", "+ping",
]


def password_sha256(password: str) -> str:
    return hashlib.sha256(password.encode()).hexdigest()


def acl_rules(gateway: Gateway, prefix: str | None = None) -> list[str]:
    prefix = prefix or channel_prefix()
    keys = [protocol.gateway_keys_pattern(prefix, gateway.name), *protocol.channel_layer_key_patterns(prefix)]
    return ["reset", "on", f"#{gateway.redis_password_sha256}", *(f"~{k}" for k in keys), "resetchannels",
            *GATEWAY_COMMANDS]


def apply_user(gateway: Gateway, client: redis.Redis | None = None) -> None:
    """Create or update the gateway's Redis user from the stored hash (no-op without one)."""
    if not gateway.redis_password_sha256:
        return
    (client or redis_client()).execute_command("ACL", "SETUSER", gateway.redis_user, *acl_rules(gateway))


def user_is_current(gateway: Gateway, client: redis.Redis | None = None) -> bool:
    """Whether Redis has the gateway's user with the stored password (it may have restarted)."""
    found = (client or redis_client()).acl_getuser(gateway.redis_user)
    return bool(found) and list(found.get("passwords") or []) == [gateway.redis_password_sha256]


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


post_delete.connect(_gateway_deleted, sender=Gateway, dispatch_uid="fleet.gateways.gateway_deleted")
