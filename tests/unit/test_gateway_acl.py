"""Least privilege, checked against Debian's redis-server (7.x, what the images and CI run): a
gateway's Redis user, made by ``manage.py add_gateway``, can do its job (its queue, its
streams, its heartbeat, lease and config) and nothing else: no other gateway's keys, no keys
of its own beyond those, nothing it may only read written, no Channels layer, no scripts, no
administration. Running add_gateway again locks the old password out."""
from __future__ import annotations

import asyncio
import hashlib
import shutil
import stat
from pathlib import Path

import pytest
import redis
from channels_redis.core import RedisChannelLayer
from django.core.management import call_command
from django.core.management.base import CommandError

from lifecycle_site import local_redis
from lifecycle_site.fleet.models import Gateway
from lifecycle_site.gateway_link import gateways
from ros_gateway.shared import protocol
from tests import stack


@pytest.fixture(scope="module")
def debian_redis(tmp_path_factory):
    binary = shutil.which("redis-server")
    assert binary, "Debian's redis-server is needed for the ACL tests (apt-get install redis-server)"
    port = stack.free_port()
    process = local_redis.start(port, tmp_path_factory.mktemp("acl-redis"), binary=binary)
    try:
        yield f"redis://127.0.0.1:{port}/0"
    finally:
        process.terminate()
        process.wait(5)


@pytest.fixture
def site(db, debian_redis, settings):
    settings.REDIS_URL = debian_redis  # the site's own (default) user: it manages the gateways' users
    yield redis.Redis.from_url(debian_redis)
    gateways.forget()


def add_gateway(name: str, env_file: Path) -> dict[str, str]:
    call_command("add_gateway", name, "--env-file", str(env_file))
    return dict(line.split("=", 1) for line in env_file.read_text().splitlines())


def test_add_gateway_writes_a_private_env_file_and_rotating_locks_the_old_password_out(site, tmp_path, capsys):
    env_file = tmp_path / "cell-x.env"
    env_file.write_text("left over\n")
    env_file.chmod(0o644)
    env = add_gateway("cell-x", env_file)
    assert stat.S_IMODE(env_file.stat().st_mode) == 0o600
    assert set(env) == {"LIFECYCLE_GATEWAY_NAME", "REDIS_URL", "LIFECYCLE_CHANNEL_PREFIX"}
    assert env["LIFECYCLE_GATEWAY_NAME"] == "cell-x" and env["LIFECYCLE_CHANNEL_PREFIX"] == gateways.channel_prefix()
    old = redis.Redis.from_url(env["REDIS_URL"])
    assert old.connection_pool.connection_kwargs["username"] == "gw-cell-x"
    password = old.connection_pool.connection_kwargs["password"]
    assert Gateway.objects.get(name="cell-x").redis_password_sha256 == hashlib.sha256(password.encode()).hexdigest()
    assert password not in capsys.readouterr().out  # written to the file only
    assert old.ping()

    rotated = add_gateway("cell-x", env_file)
    assert rotated["REDIS_URL"] != env["REDIS_URL"]
    with pytest.raises(redis.ConnectionError):  # its open connection was closed, and it cannot log in again
        old.ping()
    with pytest.raises(redis.AuthenticationError):
        redis.Redis.from_url(env["REDIS_URL"]).ping()
    assert redis.Redis.from_url(rotated["REDIS_URL"]).ping()

    call_command("add_gateway", "cell-x")  # without a file: printed, one KEY=VALUE a line
    printed = capsys.readouterr().out.splitlines()
    assert [line.split("=", 1)[0] for line in printed] == ["LIFECYCLE_GATEWAY_NAME", "REDIS_URL",
                                                           "LIFECYCLE_CHANNEL_PREFIX"]
    with pytest.raises(redis.AuthenticationError):
        redis.Redis.from_url(rotated["REDIS_URL"]).ping()
    with pytest.raises(CommandError, match="lower-case"):
        call_command("add_gateway", "Cell X")


def test_a_gateway_user_can_do_its_job_and_nothing_else(site, tmp_path):
    prefix = gateways.channel_prefix()
    mine = redis.Redis.from_url(add_gateway("cell-x", tmp_path / "x.env")["REDIS_URL"])
    add_gateway("cell-y", tmp_path / "y.env")

    # Its job: commands in, replies out, facts, logs and live updates, heartbeat, lease, config, verdicts.
    site.lpush(protocol.command_queue(prefix, "cell-x"), '{"command": "ping"}')
    assert mine.brpop([protocol.command_queue(prefix, "cell-x")], timeout=1)[1] == b'{"command": "ping"}'
    reply = protocol.reply_key(prefix, "cell-x", "r1")
    with mine.pipeline(transaction=True) as pipe:
        pipe.lpush(reply, "{}")
        pipe.expire(reply, protocol.REPLY_TTL_S)
        pipe.execute()
    assert mine.set(protocol.claim_key(prefix, "cell-x", "r1"), "{}", nx=True, ex=protocol.CLAIM_TTL_S)
    for stream in (protocol.facts_stream(prefix, "cell-x"), protocol.logs_stream(prefix, "cell-x"),
                   protocol.live_stream(prefix, "cell-x")):
        mine.xadd(stream, {"f": "{}"}, maxlen=100, approximate=False)
    mine.set(protocol.beat_key(prefix, "cell-x"), "{}")
    lease = protocol.lease_key(prefix, "cell-x")
    assert mine.set(lease, "me", nx=True, px=10_000)
    assert mine.pexpire(lease, 10_000)
    with mine.pipeline(transaction=True) as pipe:  # the lease's compare-and-delete
        pipe.watch(lease)
        assert pipe.get(lease) == b"me"
        pipe.multi()
        pipe.delete(lease)
        assert pipe.execute() == [1]
    site.set(protocol.config_key(prefix, "cell-x"), '{"robots": []}')
    assert mine.get(protocol.config_key(prefix, "cell-x")) == b'{"robots": []}'
    site.set(protocol.verdict_key(prefix, "cell-x", "abc"), '{"status": "failed"}')
    assert mine.get(protocol.verdict_key(prefix, "cell-x", "abc")) == b'{"status": "failed"}'

    # Nothing else: another gateway's queue, streams and keys; what the site writes for it; keys of
    # its own beyond those it needs; the Channels layer; scripts (they block Redis for everyone);
    # another database; the site's lease; administration.
    other_queue = protocol.command_queue(prefix, "cell-y")
    forbidden = [
        lambda: mine.lpush(other_queue, "{}"),
        lambda: mine.lpush(protocol.command_queue(prefix, "cell-x"), "x" * 1000),  # its own queue: take only
        lambda: mine.rpush(protocol.command_queue(prefix, "cell-x"), "{}"),
        lambda: mine.brpop([other_queue], timeout=1),
        lambda: mine.get(other_queue),
        lambda: mine.get(protocol.config_key(prefix, "cell-y")),
        lambda: mine.set(protocol.beat_key(prefix, "cell-y"), "{}"),
        lambda: mine.xadd(protocol.facts_stream(prefix, "cell-y"), {"f": "{}"}),
        lambda: mine.xadd(protocol.live_stream(prefix, "cell-y"), {"m": "{}"}),
        lambda: mine.xreadgroup(protocol.INGEST_GROUP, "site", {protocol.facts_stream(prefix, "cell-y"): ">"}),
        lambda: mine.xrange(protocol.facts_stream(prefix, "cell-x")),
        lambda: mine.set(protocol.config_key(prefix, "cell-x"), '{"robots": [{"name": "agv-9"}]}'),
        lambda: mine.delete(protocol.config_key(prefix, "cell-x")),
        lambda: mine.set(protocol.verdict_key(prefix, "cell-x", "abc"), "x"),
        lambda: mine.set(protocol.gateway_key(prefix, "cell-x", "anything"), "x" * 1000),
        lambda: mine.zadd(f"{prefix}:group:fleet", {"x": 1}),
        lambda: mine.zremrangebyscore(f"{prefix}:group:fleet", "-inf", "+inf"),
        lambda: mine.lpush(f"{prefix}specific.abc!def", "x"),
        lambda: mine.publish("anything", "x"),
        lambda: mine.set(protocol.ingest_lease_key(prefix), "me"),
        lambda: mine.set(f"{prefix}:site:quarantined", "x"),
        lambda: mine.eval("return 1", 0),
        lambda: mine.eval("local i=0 while i<1300000000 do i=i+1 end return i", 0),
        lambda: mine.evalsha("0" * 40, 0),
        lambda: mine.execute_command("FCALL", "f", 0),
        lambda: mine.execute_command("FUNCTION", "LIST"),
        lambda: mine.execute_command("SELECT", 1),
        lambda: mine.execute_command("SWAPDB", 0, 1),
        lambda: mine.flushall(),
        lambda: mine.config_get("*"),
        lambda: mine.keys("*"),
        lambda: mine.scan(),
        lambda: mine.info(),
        lambda: mine.execute_command("ACL", "LIST"),
        lambda: mine.execute_command("CLIENT", "LIST"),
        lambda: mine.execute_command("CLIENT", "KILL", "USER", "gw-cell-y"),
        lambda: mine.execute_command("CLIENT", "PAUSE", 1000),
        lambda: mine.execute_command("SHUTDOWN", "NOSAVE"),
    ]
    for attempt in forbidden:
        with pytest.raises(redis.exceptions.NoPermissionError):
            attempt()
    assert mine.ping()  # still connected, still the same Redis


def test_a_gateway_user_cannot_reach_the_channels_layer(site, debian_redis, tmp_path):
    """F4: no group_send into the pages' groups (fake states, fake audit rows), no group_add of
    its own channel (reading other cells' updates), no deleting a group's members."""
    prefix = gateways.channel_prefix()
    site_layer = RedisChannelLayer(hosts=[debian_redis], prefix=prefix)
    gateway_layer = RedisChannelLayer(hosts=[add_gateway("cell-x", tmp_path / "x.env")["REDIS_URL"]], prefix=prefix)

    async def scenario() -> list:
        try:
            channel = await site_layer.new_channel()
            await site_layer.group_add(protocol.FLEET_GROUP, channel)
            tried = []
            for attempt in (lambda: gateway_layer.group_send(protocol.FLEET_GROUP, {"type": "node.state"}),
                            lambda: gateway_layer.group_add(protocol.FLEET_GROUP, "own-channel"),
                            lambda: gateway_layer.group_discard(protocol.FLEET_GROUP, channel)):
                try:
                    await attempt()
                    tried.append("allowed")
                except redis.exceptions.NoPermissionError:
                    tried.append("refused")
            with pytest.raises(asyncio.TimeoutError):  # nothing arrived
                await asyncio.wait_for(site_layer.receive(channel), 0.5)
            return tried
        finally:
            await gateway_layer.close_pools()
            await site_layer.close_pools()

    assert asyncio.run(scenario()) == ["refused"] * 3


def test_deleting_a_gateway_drops_its_redis_user_and_closes_its_connections(
    site, tmp_path, django_capture_on_commit_callbacks
):
    env = add_gateway("cell-gone", tmp_path / "cell-gone.env")
    connected = redis.Redis.from_url(env["REDIS_URL"])
    assert connected.ping()
    with django_capture_on_commit_callbacks(execute=True):
        Gateway.objects.get(name="cell-gone").delete()
    assert not site.acl_getuser("gw-cell-gone")
    with pytest.raises(redis.ConnectionError):
        connected.ping()
