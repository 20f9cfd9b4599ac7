"""Live updates from a request of the server are handed to its event loop: the answer does not
wait for them, they still arrive, and a loop that cannot send bounds how many wait."""
from __future__ import annotations

import asyncio
import logging
import threading
import time

import pytest
from asgiref.sync import async_to_sync
from channels.layers import get_channel_layer

from lifecycle_site.gateway_link.gateways import redis_client
from lifecycle_site.ingest import live_updates
from ros_gateway.shared import protocol

GROUP = "unit-live-updates"


@pytest.fixture
def server_loop(redis_server):
    """An event loop in a thread of its own, as daphne's; set as the server's for the test."""
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    token = live_updates.server_loop.set(loop)
    yield loop
    live_updates.server_loop.reset(token)
    loop.call_soon_threadsafe(loop.stop)
    thread.join(5)
    loop.close()


def busy(loop: asyncio.AbstractEventLoop, seconds: float) -> None:
    """Keep the loop from running anything else for a while (a loop serving many sockets)."""
    loop.call_soon_threadsafe(time.sleep, seconds)


def wait_until(check, timeout: float) -> None:
    end = time.monotonic() + timeout
    while not check():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.01)


def test_a_request_does_not_wait_for_its_push_and_the_push_arrives(server_loop):
    layer = get_channel_layer()
    channel = async_to_sync(layer.new_channel)()
    async_to_sync(layer.group_add)(GROUP, channel)
    busy(server_loop, 0.5)
    began = time.monotonic()
    live_updates.push([(GROUP, {"type": "audit.record", "record": {"id": 7}})])
    assert time.monotonic() - began < 0.1, "the request waited for the server's loop"
    assert live_updates.pending() == 1
    message = async_to_sync(asyncio.wait_for)(layer.receive(channel), 5)
    assert message == {"type": "audit.record", "record": {"id": 7}}
    wait_until(lambda: live_updates.pending() == 0, 5)


def test_pushes_waiting_for_the_loop_are_bounded(server_loop, monkeypatch, caplog):
    monkeypatch.setattr(live_updates, "MAX_PENDING", 2)
    busy(server_loop, 1.0)
    with caplog.at_level(logging.WARNING, logger="lifecycle_site.ingest.live_updates"):
        for n in range(3):
            live_updates.push([(GROUP, {"type": "audit.record", "record": {"id": n}})])
    assert live_updates.pending() == 2
    assert "dropped 1 live updates: 2 are still waiting" in caplog.text
    wait_until(lambda: live_updates.pending() == 0, 5)


def test_outside_the_server_a_push_is_sent_before_it_returns(redis_server):
    """The ingest process (no server loop) sends and waits, as before."""
    layer = get_channel_layer()
    channel = async_to_sync(layer.new_channel)()
    async_to_sync(layer.group_add)(GROUP, channel)
    live_updates.push([(GROUP, {"type": "audit.record", "record": {"id": 1}})])
    assert live_updates.pending() == 0
    assert async_to_sync(asyncio.wait_for)(layer.receive(channel), 5)["record"] == {"id": 1}


def test_outside_the_server_pushes_share_one_kept_loop_and_a_hung_one_is_bounded(redis_server, monkeypatch,
                                                                                   caplog):
    """One loop (and so one Redis connection pool) for every push of the process, not one per
    push; a push that cannot go out within SEND_TIMEOUT_S is given up and logged."""
    live_updates.push([(GROUP, {"type": "audit.record", "record": {"id": 2}})])
    connections = redis_client().info("stats")["total_connections_received"]
    for n in range(20):
        live_updates.push([(GROUP, {"type": "audit.record", "record": {"id": n}})])
    assert redis_client().info("stats")["total_connections_received"] - connections <= 2  # this test's own
    loop = live_updates._own_loop()
    monkeypatch.setattr(live_updates, "SEND_TIMEOUT_S", 0.2)
    busy(loop, 1.0)
    began = time.monotonic()
    with caplog.at_level(logging.WARNING, logger="lifecycle_site.ingest.live_updates"):
        live_updates.push([(GROUP, {"type": "audit.record", "record": {"id": 4}})])
    assert time.monotonic() - began < 0.5
    assert "could not push 1 of 1 live updates: not sent within 0.2 s" in caplog.text


def test_stored_records_reach_their_node_pages_and_once_the_audit_pages(db):
    from django.utils import timezone

    from lifecycle_site.audit.models import TransitionRecord
    from lifecycle_site.fleet.models import ManagedNode, Robot

    robot = Robot.objects.create(name="unit-live", domain_id=98)
    node = ManagedNode.objects.create(robot=robot, name="/lidar")
    now = timezone.now()
    records = [
        TransitionRecord.objects.create(node=node, robot=robot, robot_name=robot.name, node_name=node.name,
                                        transition_label="configure", outcome="succeeded", source="api",
                                        requested_at=now)
        for _ in range(2)
    ]
    groups = [group for group, _ in live_updates.record_messages(records)]
    assert groups == [protocol.node_group(node.key)] * 2 + [live_updates.AUDIT_GROUP]
    assert live_updates.record_messages([]) == []
    # Parameter records go to the audit pages only (their parameter mode).
    assert live_updates.record_messages([], [object()]) == [live_updates.AUDIT_STORED]
