"""Operators see the gateways: the fleet page groups robots under their gateway with its health,
the banner names the gateway that is offline (and only its robots), a node's page names its
gateway, live pages follow a gateway going away, the admin lists them, the API reports them."""
from __future__ import annotations

import time

import pytest
from asgiref.sync import async_to_sync
from channels.routing import URLRouter
from channels.testing import WebsocketCommunicator
from django.test import Client

from lifecycle_site.fleet.models import Gateway, ManagedNode, Robot
from ros_gateway.shared import state_machine as sm
from tests import stack
from tests.conftest import make_user, session_of
from tests.unit.sockets import receive_until


@pytest.fixture
def two_cells(db, redis_server):
    for name, domain in (("cell-up", 50), ("cell-down", 51)):
        robot = Robot.objects.create(name=f"{name}-agv", domain_id=domain,
                                     gateway=Gateway.objects.create(name=name, description=f"hall {domain}"))
        ManagedNode.objects.create(robot=robot, name="/lidar", alive=True, state_id=sm.ACTIVE, state_label="active")
    stack.write_beat("cell-up", version="2.0.1", nodes=1, domains=[50],
                     dds={"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET", "ROS_STATIC_PEERS": "10.0.0.7"})
    stack.write_beat("cell-down", at=time.time() - 3600 * 3, version="1.9.0")
    Gateway.objects.filter(name="cell-down").update(logs_dropped=12, backlog=40)


def test_the_fleet_page_groups_robots_by_gateway_with_its_health(viewer_client, two_cells):
    page = viewer_client.get("/").content.decode()
    up, down = page.index('id="gateway-cell-up"'), page.index('id="gateway-cell-down"')
    assert page.index('id="robot-cell-up-agv"') > up and page.index('id="robot-cell-down-agv"') > down
    head_up = page[page.index('id="gateway-cell-up-head"'):page.index("</header>", up)]
    assert 'data-gateway-online="true"' in head_up and ">online</span>" in head_up
    assert "version 2.0.1" in head_up and "discovery SUBNET · peers 10.0.0.7" in head_up
    head_down = page[page.index('id="gateway-cell-down-head"'):page.index("</header>", down)]
    assert 'data-gateway-online="false"' in head_down and ">offline</span>" in head_down
    assert "since " in head_down and "3 h ago" in head_down and "12 log lines dropped" in head_down
    assert "backlog 40" in head_down
    banner = page[page.index('id="gateway-banner"'):page.index("</div>", page.index('id="gateway-banner"'))]
    assert "hidden" not in banner.split(">")[0]
    assert "The ROS gateway cell-down is offline (no heartbeat since" in banner and "cell-down-agv shows" in banner
    assert "cell-up" not in banner


def test_a_nodes_page_names_its_gateway_and_the_banner_only_its_own(viewer_client, two_cells):
    page = viewer_client.get("/nodes/cell-up-agv.lidar/").content.decode()
    assert "gateway cell-up" in page
    assert 'id="gateway-banner"' in page and "is offline" not in page
    page = viewer_client.get("/nodes/cell-down-agv.lidar/").content.decode()
    assert "gateway cell-down" in page and "The ROS gateway cell-down is offline" in page
    logs = viewer_client.get("/logs/robot/cell-down-agv/").content.decode()
    assert "gateway cell-down" in logs and "The ROS gateway cell-down is offline" in logs


def test_the_api_lists_gateways_and_each_robots_gateway(viewer_client, two_cells):
    gateways = {g["name"]: g for g in viewer_client.get("/api/v1/gateways").json()["gateways"]}
    up, down = gateways["cell-up"], gateways["cell-down"]
    assert (up["online"], up["status"], up["version"], up["robots"], up["domains"]) == (
        True, "online", "2.0.1", ["cell-up-agv"], [50])
    assert (down["online"], down["status"], down["logs_dropped"], down["backlog"]) == (False, "offline", 12, 40)
    assert down["reason"].startswith("no heartbeat since ") and down["last_beat"]
    body = viewer_client.get("/api/v1/robots").json()
    robots = {r["name"]: r for r in body["robots"]}
    assert body["gateway_online"] is False  # one gateway with robots is not
    assert (robots["cell-up-agv"]["gateway"], robots["cell-up-agv"]["gateway_online"],
            robots["cell-up-agv"]["online"]) == ("cell-up", True, True)
    assert (robots["cell-down-agv"]["gateway"], robots["cell-down-agv"]["online"]) == ("cell-down", False)


def test_the_admin_lists_gateways_without_their_password_hash(db, redis_server, two_cells):
    gateway = Gateway.objects.get(name="cell-up")
    gateway.redis_password_sha256 = "ab" * 32
    gateway.version = "2.0.1"  # as the ingest process copies it from the heartbeat
    gateway.save()
    admin = make_user("ada-gateways", "admin")
    admin.is_superuser = True
    admin.save()
    client = Client()
    client.force_login(admin)
    listing = client.get("/admin/fleet/gateway/").content.decode()
    assert "cell-up" in listing and "cell-down" in listing and "2.0.1" in listing
    detail = client.get(f"/admin/fleet/gateway/{gateway.pk}/change/").content.decode()
    assert "gw-cell-up" in detail and "ab" * 32 not in detail
    assert "cell-up-agv" in detail  # its robots


def test_a_live_fleet_page_follows_a_gateway_going_away(transactional_db, redis_server, settings):
    from lifecycle_site.dashboard import consumers
    from lifecycle_site.dashboard.routing import websocket_urlpatterns

    settings.CHANNEL_LAYERS = {"default": {"BACKEND": "channels.layers.InMemoryChannelLayer"}}
    robot = Robot.objects.create(name="live-agv", domain_id=52, gateway=Gateway.objects.create(name="cell-live"))
    ManagedNode.objects.create(robot=robot, name="/lidar", alive=True, state_id=sm.ACTIVE, state_label="active")
    stack.write_beat("cell-live")
    user = make_user("olga-live", "operator")
    session = session_of(user)

    async def scenario():
        communicator = WebsocketCommunicator(URLRouter(websocket_urlpatterns), "/ws/fleet/")
        communicator.scope["user"] = user
        communicator.scope["session"] = session
        assert (await communicator.connect(timeout=5))[0]
        try:
            banner = await receive_until(communicator, 'id="gateway-banner"', timeout=8)
            assert "hidden" in banner.split(">")[0]
            stack.write_beat("cell-live", stopped=True)
            banner = await receive_until(communicator, "The ROS gateway cell-live is offline (it stopped at",
                                         timeout=8)
            assert "live-agv shows" in banner
            head = await receive_until(communicator, 'id="gateway-cell-live-head"', timeout=8)
            assert 'hx-swap-oob="true"' in head and 'data-gateway-online="false"' in head and ">stopped<" in head
        finally:
            await communicator.disconnect()

    original = consumers.GATEWAY_CHECK_S
    consumers.GATEWAY_CHECK_S = 0.2
    try:
        async_to_sync(scenario)()
    finally:
        consumers.GATEWAY_CHECK_S = original
