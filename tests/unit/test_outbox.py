"""The gateway's outbox on the real Redis: a command's reply goes over with the facts queued
before it, in one round trip and all or nothing, and the streams stay in order."""
from __future__ import annotations

import asyncio
import json

import pytest
from django.conf import settings

from lifecycle_site.gateway_link.gateways import channel_prefix
from ros_gateway.outbox import FLUSH_BATCH, Outbox
from ros_gateway.relay import Relay
from ros_gateway.shared import protocol
from tests import stack
from tests.gateway_part import clear_streams

GATEWAY = "unit-outbox"


def run(coroutine):
    return asyncio.run(coroutine)


async def outbox_with(redis_url: str) -> tuple[Relay, Outbox]:
    relay = Relay(GATEWAY, redis_url, channel_prefix())
    return relay, Outbox(relay, GATEWAY, relay.instance)


def stream_seqs() -> list[int]:
    entries = stack.redis_client().xrange(protocol.gateway_key(channel_prefix(), GATEWAY, "facts"))
    return [json.loads(fields[b"f"])["seq"] for _, fields in entries]


@pytest.fixture
def clean(redis_server):
    clear_streams(GATEWAY)
    yield
    clear_streams(GATEWAY)


def test_a_reply_goes_over_with_the_facts_queued_before_it_in_order(clean):
    async def scenario():
        relay, outbox = await outbox_with(settings.REDIS_URL)
        for n in range(3):
            outbox.emit(protocol.NODE_STATE, robot="r", node=f"/n{n}", state_id=2)
        key, message = relay.reply_parts("req-1", {"ok": True})
        assert await outbox.reply(key, message, protocol.REPLY_TTL_S)
        assert not outbox.facts.queue and outbox.facts.sent == 3
        outbox.emit(protocol.NODE_STATE, robot="r", node="/n3", state_id=3)
        assert await outbox.flush()
        await relay.close()
        return key

    key = run(scenario())
    assert stream_seqs() == [1, 2, 3, 4]
    # Those handed over with the reply are marked (the ingest process lets them settle).
    entries = stack.redis_client().xrange(protocol.gateway_key(channel_prefix(), GATEWAY, "facts"))
    assert [fields.get(protocol.REPLIED.encode()) for _, fields in entries] == [b"1", b"1", b"1", None]
    client = stack.redis_client()
    assert 0 < client.ttl(key) <= protocol.REPLY_TTL_S
    assert json.loads(client.lpop(key)) == {"request_id": "req-1", "ok": True}


def test_with_redis_unreachable_nothing_is_handed_over_and_the_facts_stay_queued(clean):
    async def scenario():
        relay, outbox = await outbox_with("redis://127.0.0.1:1/0")  # nothing listens there
        fact = outbox.emit(protocol.NODE_STATE, robot="r", node="/n", state_id=2)
        key, message = relay.reply_parts("req-2", {"ok": True, "facts": [fact]})
        handed = await outbox.reply(key, message, protocol.REPLY_TTL_S)
        queued = len(outbox.facts.queue)
        await relay.close()
        return handed, queued

    handed, queued = run(scenario())
    assert (handed, queued) == (False, 1)
    assert stream_seqs() == []


def test_a_backlog_longer_than_a_batch_is_left_to_the_flusher(clean):
    async def scenario():
        relay, outbox = await outbox_with(settings.REDIS_URL)
        for n in range(FLUSH_BATCH + 1):
            outbox.emit(protocol.NODE_STATE, robot="r", node=f"/n{n}", state_id=2)
        key, message = relay.reply_parts("req-3", {"ok": True})
        handed = await outbox.reply(key, message, protocol.REPLY_TTL_S)
        await relay.close()
        return handed

    assert run(scenario()) is False
    assert stream_seqs() == []


def test_a_new_process_keeps_what_its_predecessor_left_unread_and_stays_within_its_quota(clean):
    """Each XADD carries the exact MAXLEN of the newest entries within the stream's share of the
    quota (ros_gateway/budget.py). A new process counts what its predecessor left (the ingest
    process stopped meanwhile): its first XADD must not trim those (a fresh count would be 1)."""
    async def scenario(facts: int, quota: int | None = None) -> None:
        relay, outbox = await outbox_with(settings.REDIS_URL)
        if quota:
            outbox.set_quota(quota)
        for n in range(facts):
            outbox.emit(protocol.NODE_STATE, robot="r", node=f"/n{n}", state_id=2)
        assert await outbox.flush()
        await relay.close()

    run(scenario(50))
    run(scenario(1))  # the next gateway process
    assert len(stream_seqs()) == 51
    run(scenario(3000, quota=256 * 1024))  # 3,000 facts of ~200 bytes: ~35 % of 256 KiB keeps ~350
    stream = protocol.gateway_key(channel_prefix(), GATEWAY, "facts")
    kept = stack.redis_client().memory_usage(stream, samples=0)
    assert kept <= 256 * 1024 * protocol.STREAM_SHARES["facts"] * 1.1, kept
    assert 0 < stack.redis_client().xlen(stream) < 1000
