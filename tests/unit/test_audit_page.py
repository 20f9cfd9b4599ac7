"""The audit history page: outcomes named as the filter names them, a filter it cannot apply
said so (not an empty history), and its first page following new records over a socket."""
from __future__ import annotations

import pytest
from asgiref.sync import async_to_sync
from channels.layers import get_channel_layer
from channels.routing import URLRouter
from channels.testing import WebsocketCommunicator
from django.test import Client
from django.utils import timezone

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import ManagedNode, Robot
from tests.conftest import make_user, session_of
from tests.unit.sockets import receive_until


@pytest.fixture
def node(db):
    robot = Robot.objects.create(name="audit-agv", domain_id=97)
    return ManagedNode.objects.create(robot=robot, name="/lidar", key="audit-agv.lidar")


def record(node, outcome: str, **extra) -> TransitionRecord:
    return TransitionRecord.objects.create(node=node, robot_name=node.robot.name, node_name=node.name,
                                           transition_label="configure", outcome=outcome, source="dashboard",
                                           requested_at=timezone.now(), **extra)


def test_a_timed_out_record_reads_as_the_filter_names_it(viewer_client, node):
    record(node, "timed_out")
    page = viewer_client.get("/audit/?outcome=timed_out").content.decode()
    assert '<option value="timed_out" selected>timed out</option>' in page
    assert '<span class="outcome timed_out">timed out</span>' in page
    assert "timedout" not in page
    assert "1 record," in page


@pytest.mark.parametrize("since", ["yesterday", "2026-13-01", "23.11.2026 14:00"])
def test_a_filter_that_cannot_be_applied_says_why_instead_of_showing_no_records(viewer_client, node, since):
    record(node, "succeeded")
    page = viewer_client.get("/audit/", {"since": since}).content.decode()
    assert "From (UTC): Not a date and time: write it like 2026-11-23 14:05 (UTC)" in page
    assert "No records shown: the filter cannot be applied." in page
    assert "0 records" not in page
    assert "ws/audit/" not in page  # nothing to follow


def test_dates_as_the_calendar_and_people_write_them_are_applied(viewer_client, node):
    record(node, "succeeded")
    for since in ("2020-01-01T00:00", "2020-01-01 00:00", "2020-01-01"):
        page = viewer_client.get("/audit/", {"since": since}).content.decode()
        assert "1 record," in page, since


@pytest.fixture
def memory_layer(settings):
    settings.CHANNEL_LAYERS = {"default": {"BACKEND": "channels.layers.InMemoryChannelLayer"}}


def test_the_first_page_follows_new_records_of_its_filter(transactional_db, memory_layer, monkeypatch):
    from lifecycle_site.dashboard import audit_consumer, consumers
    from lifecycle_site.dashboard.routing import websocket_urlpatterns

    monkeypatch.setattr(consumers, "GATEWAY_CHECK_S", 0.3)
    robot = Robot.objects.create(name="audit-agv", domain_id=97)
    lidar = ManagedNode.objects.create(robot=robot, name="/lidar", key="audit-agv.lidar")
    old = record(lidar, "failed", error="before the page")
    user = make_user("vera-audit", "viewer")
    session = session_of(user)
    browser = Client()
    browser.force_login(user)
    page = browser.get("/audit/?outcome=failed").content.decode()
    assert f'ws-connect="/ws/audit/?outcome=failed&amp;shown={old.id}"' in page

    async def scenario():
        communicator = WebsocketCommunicator(URLRouter(websocket_urlpatterns),
                                             f"/ws/audit/?outcome=failed&shown={old.id}")
        communicator.scope["user"] = user
        communicator.scope["session"] = session
        connected, _ = await communicator.connect(timeout=5)
        assert connected
        try:
            await async_db(record, lidar, "succeeded", error="not failed")
            await async_db(record, lidar, "failed", error="lidar cable loose")
            # Announced: read at once. (Without it the poll finds it within GATEWAY_CHECK_S.)
            await get_channel_layer().group_send(audit_consumer.AUDIT_GROUP, {"type": "audit.record", "record": {}})
            count = await receive_until(communicator, 'id="audit-count"')
            assert 'id="audit-count" hx-swap-oob="true">2 records' in count
            update = await communicator.receive_from(timeout=5)
            assert update.startswith('<tbody id="audit-rows" hx-swap-oob="true">') and "lidar cable loose" in update
            assert "not failed" not in update and "before the page" in update
            assert update.count('class="outcome-failed new"') == 1
            await async_db(record, lidar, "failed", error="no push, polled")
            assert "3 records" in await receive_until(communicator, 'id="audit-count"')
            assert "no push, polled" in await communicator.receive_from(timeout=5)
        finally:
            await communicator.disconnect()

    async_to_sync(scenario)()


async def async_db(function, *args, **kwargs):
    from channels.db import database_sync_to_async

    return await database_sync_to_async(function)(*args, **kwargs)


def test_a_socket_with_a_filter_it_cannot_apply_is_refused(transactional_db, memory_layer):
    from lifecycle_site.dashboard.routing import websocket_urlpatterns

    user = make_user("vera-audit", "viewer")
    session = session_of(user)

    async def scenario():
        communicator = WebsocketCommunicator(URLRouter(websocket_urlpatterns), "/ws/audit/?since=yesterday")
        communicator.scope["user"] = user
        communicator.scope["session"] = session
        connected, code = await communicator.connect(timeout=5)
        assert (connected, code) == (False, 4404)

    async_to_sync(scenario)()
