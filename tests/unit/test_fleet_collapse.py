"""The fleet page at 1,000 nodes: robots of a large fleet show their counts by state instead of
their rows, open on click (kept in the URL), the name filter finds a node in any collapsed robot
(bounded), and the live socket keeps a collapsed robot's counts current without sending its rows."""
from __future__ import annotations

import re

import pytest
from asgiref.sync import async_to_sync
from channels.layers import get_channel_layer
from channels.routing import URLRouter
from channels.testing import WebsocketCommunicator
from django.db import connection
from django.test.utils import CaptureQueriesContext
from django.utils import timezone

from lifecycle_site.dashboard import snapshots
from lifecycle_site.fleet.models import ManagedNode, Robot
from lifecycle_site.fleet.serializers import node_dict
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm
from tests.conftest import make_user, session_of

ROBOTS, PER_ROBOT = 10, 100


def make_fleet(robots: int = ROBOTS, per_robot: int = PER_ROBOT, prefix: str = "big") -> list[Robot]:
    """``robots`` robots of ``per_robot`` nodes: every 10th lost, every 5th inactive, one
    configuring, the rest active."""
    made = [Robot.objects.create(name=f"{prefix}-{r}", domain_id=70 + r) for r in range(robots)]
    now = timezone.now()
    nodes = []
    for robot in made:
        for i in range(per_robot):
            state = sm.CONFIGURING if i == 1 else sm.INACTIVE if i % 5 == 0 else sm.ACTIVE
            nodes.append(ManagedNode(robot=robot, name=f"/{robot.name.replace('-', '_')}_n{i:03d}",
                                     key=f"{robot.name}.{robot.name.replace('-', '_')}_n{i:03d}",
                                     alive=i % 10 != 3, state_id=state, state_label=sm.state_label(state),
                                     last_seen=now))
    ManagedNode.objects.bulk_create(nodes)
    return made


@pytest.fixture
def big_fleet(db):
    return make_fleet()


def queries_for(client, path: str) -> tuple[int, str]:
    with CaptureQueriesContext(connection) as captured:
        response = client.get(path)
    assert response.status_code == 200
    return len(captured.captured_queries), response.content.decode()


def test_a_large_fleet_shows_its_robots_collapsed_with_their_counts(viewer_client, big_fleet):
    count, page = queries_for(viewer_client, "/")
    assert page.count('class="node-row') == 0
    assert page.count('data-collapsed="true"') == ROBOTS
    # Per robot: 10 lost (i % 10 == 3), 1 configuring (busy), 20 inactive (i % 5 == 0), the rest active.
    summary = re.search(r'<div id="robot-big-4-summary".*?</div>', page, re.S).group(0)
    assert 'data-total="100"' in summary and 'data-alive="90"' in summary
    for text in ("69 active", "20 inactive", "1 busy", "10 lost"):
        assert text in summary
    assert "Show its 100 nodes" in page and "on gateway local" in page


def test_the_fleet_page_costs_the_same_queries_at_1000_nodes_as_at_200(viewer_client, db):
    make_fleet(robots=8, per_robot=25, prefix="small")
    small, page = queries_for(viewer_client, "/")
    assert page.count('class="node-row') == 200
    make_fleet(robots=8, per_robot=100)  # 1,000 nodes in all
    large, page = queries_for(viewer_client, "/?open=big-2")
    assert large <= small
    # The small robots' rows (25 each: robots that small stay open) and the opened robot's.
    assert page.count('class="node-row') == 200 + PER_ROBOT


def test_an_opened_robot_is_in_the_url_and_shows_every_row(viewer_client, big_fleet):
    page = viewer_client.get("/?open=big-3").content.decode()
    assert page.count('class="node-row') == PER_ROBOT
    assert page.count('data-collapsed="true"') == ROBOTS - 1
    assert 'ws/fleet/?open=big-3"' in page  # the socket knows which robot the page opened
    assert "Collapse to counts" in page


def test_a_robot_opens_and_collapses_on_click(operator_client, big_fleet):
    opened = operator_client.get("/robots/big-5/nodes?open=1").content.decode()
    assert opened.count('class="node-row') == PER_ROBOT and 'data-collapsible="true"' in opened
    assert 'data-collapsed' not in opened and 'hx-post="/nodes/big-5.big_5_n007/transition"' in opened
    collapsed = operator_client.get("/robots/big-5/nodes?open=0").content.decode()
    assert 'class="node-row' not in collapsed and 'data-collapsed="true"' in collapsed and "69 active" in collapsed
    assert operator_client.get("/robots/no-such-robot/nodes?open=1").status_code == 404


def test_the_name_filter_finds_nodes_in_collapsed_robots_bounded(viewer_client, big_fleet):
    robots = ",".join(f"big-{r}" for r in range(ROBOTS))
    one = viewer_client.get(f"/fleet/find?q=big_7_n042&robots={robots}").content.decode()
    assert '<a href="/nodes/big-7.big_7_n042/">/big_7_n042</a>' in one and "1 node" in one
    many = viewer_client.get(f"/fleet/find?q=_n0&robots={robots}").content.decode()
    assert many.count("data-match=") == snapshots.FIND_MAX
    assert f"and {ROBOTS * 100 - snapshots.FIND_MAX} more" in many
    lost = viewer_client.get("/fleet/find?state=lost&robots=big-1").content.decode()
    assert lost.count("data-match=") == 10 and "big_1_n003" in lost and "big_2" not in lost
    only = viewer_client.get("/fleet/find?q=n042&robots=big-1,big-2").content.decode()
    assert only.count("data-match=") == 2
    assert viewer_client.get(f"/fleet/find?robots={robots}").content == b""  # no filter, no list
    assert "No node of the collapsed robots matches" in viewer_client.get(
        f"/fleet/find?q=zzz&robots={robots}").content.decode()


def test_a_small_fleet_is_not_collapsed(viewer_client, db):
    make_fleet(robots=3, per_robot=100)  # 300 nodes: the limit itself
    page = viewer_client.get("/").content.decode()
    assert page.count('class="node-row') == 300 and "data-collapsible" not in page


def test_the_live_page_counts_a_collapsed_robot_and_sends_rows_only_of_opened_ones(
        transactional_db, redis_server, settings):
    from lifecycle_site.dashboard.routing import websocket_urlpatterns

    settings.CHANNEL_LAYERS = {"default": {"BACKEND": "channels.layers.InMemoryChannelLayer"}}
    make_fleet()
    user = make_user("olga-big", "operator")
    session = session_of(user)
    node = ManagedNode.objects.select_related("robot").get(key="big-4.big_4_n012")  # active
    other = ManagedNode.objects.select_related("robot").get(key="big-6.big_6_n012")
    layer = get_channel_layer()

    def pushed(row: ManagedNode, state_id: int) -> dict:
        row.state_id = state_id
        return {"type": "node.state", "node": node_dict(row)}

    async def receive_until(communicator, text: str) -> str:
        while True:
            message = await communicator.receive_from(timeout=8)
            if text in message:
                return message

    async def scenario():
        communicator = WebsocketCommunicator(URLRouter(websocket_urlpatterns), "/ws/fleet/?open=big-6")
        communicator.scope["user"] = user
        communicator.scope["session"] = session
        assert (await communicator.connect(timeout=10))[0]
        try:
            snapshot = await receive_until(communicator, 'id="robots"')
            assert snapshot.count('class="node-row') == PER_ROBOT  # big-6's rows only
            await layer.group_send(protocol.FLEET_GROUP, pushed(node, sm.INACTIVE))
            summary = await receive_until(communicator, 'id="robot-big-4-summary"')
            assert "68 active" in summary and "21 inactive" in summary and "node-row" not in summary
            await layer.group_send(protocol.FLEET_GROUP, pushed(other, sm.INACTIVE))  # opened: its row
            row = await receive_until(communicator, 'id="node-big-6__big_6_n012"')
            assert "state-inactive" in row
            # The page opens big-4 (it fetched the rows itself; they come again from here, as
            # a change may have come between) and collapses big-6.
            await communicator.send_to(text_data='{"open": ["big-4"]}')
            rows = await receive_until(communicator, 'id="node-big-4__big_4_n099"')
            assert rows.count('class="node-row') == PER_ROBOT and 'hx-swap-oob="true"' in rows
            await layer.group_send(protocol.FLEET_GROUP, pushed(node, sm.ACTIVE))
            row = await receive_until(communicator, 'id="node-big-4__big_4_n012"')
            assert "state-active" in row
            await layer.group_send(protocol.FLEET_GROUP, pushed(other, sm.ACTIVE))
            summary = await receive_until(communicator, 'id="robot-big-6-summary"')
            assert "69 active" in summary and "20 inactive" in summary
            # A page that reconnects with an older URL gets the robots it shows sent again as it wants them.
            await communicator.send_to(text_data='{"open": [], "resync": true}')
            section = await receive_until(communicator, 'id="robot-big-4"')
            assert 'data-collapsed="true"' in section and "node-row" not in section
        finally:
            await communicator.disconnect()

    async_to_sync(scenario)()
