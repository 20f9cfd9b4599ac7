"""The node page's socket (dashboard/node_consumers.py): what it sends as it opens clears only the
transition results shown before the socket opened (live.js marks them data-before-socket); a live
update of another state clears any. (A click made while the socket opened was answered with its
result, then the snapshot read before the transition was stored arrived and deleted that result:
seen in CI.)"""
from __future__ import annotations

from asgiref.sync import async_to_sync
from channels.layers import get_channel_layer
from channels.routing import URLRouter
from channels.testing import WebsocketCommunicator

from lifecycle_site.dashboard.snapshots import node_dict
from lifecycle_site.fleet.models import Gateway, ManagedNode, Robot
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm
from tests import stack
from tests.conftest import make_user, session_of
from tests.unit.sockets import receive_until

CLEARS_RESULTS = 'hx-swap-oob="delete:#transition-result > .result:not('
CLEARS_EARLIER_RESULTS = 'hx-swap-oob="delete:#transition-result > .result[data-before-socket]:not('


def test_the_snapshot_clears_only_results_older_than_the_socket_a_live_update_any_of_another_state(
        transactional_db, redis_server, settings):
    from lifecycle_site.dashboard.routing import websocket_urlpatterns

    settings.CHANNEL_LAYERS = {"default": {"BACKEND": "channels.layers.InMemoryChannelLayer"}}
    robot = Robot.objects.create(name="nc-agv", domain_id=53, gateway=Gateway.objects.create(name="cell-nc"))
    node = ManagedNode.objects.create(robot=robot, name="/lidar", alive=True, state_id=sm.INACTIVE,
                                      state_label="inactive")
    stack.write_beat("cell-nc")
    user = make_user("olga-nc", "operator")
    session = session_of(user)

    async def scenario():
        communicator = WebsocketCommunicator(URLRouter(websocket_urlpatterns), f"/ws/nodes/{node.key}/")
        communicator.scope["user"] = user
        communicator.scope["session"] = session
        assert (await communicator.connect(timeout=5))[0]
        try:
            snapshot = await receive_until(communicator, 'id="node-state"')
            assert "state-inactive" in snapshot and CLEARS_EARLIER_RESULTS in snapshot
            assert CLEARS_RESULTS not in snapshot
            node.state_id = sm.ACTIVE
            await get_channel_layer().group_send(protocol.node_group(node.key),
                                                 {"type": "node.state", "node": node_dict(node)})
            live = await receive_until(communicator, 'id="node-state"')
            assert "state-active" in live and CLEARS_RESULTS in live
            assert f":not([data-for='up-{sm.ACTIVE}-" in live  # all but a result about the state shown
        finally:
            await communicator.disconnect()

    async_to_sync(scenario)()
