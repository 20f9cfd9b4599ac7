"""The Modes page's socket (dashboard/mode_consumer.py): the robot's drift drawn as it opens, drawn
again as soon as one of its nodes changes state (the page shows drift made by another tool without
polling), and not sent again when nothing it shows changed."""
from __future__ import annotations

import asyncio

from asgiref.sync import async_to_sync
from channels.db import database_sync_to_async
from channels.layers import get_channel_layer
from channels.routing import URLRouter
from channels.testing import WebsocketCommunicator
from django.utils import timezone

from lifecycle_site.dashboard.snapshots import node_dict
from lifecycle_site.fleet.models import Gateway, ManagedNode, Robot
from lifecycle_site.modes.models import CurrentMode, Mode
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm
from tests import stack
from tests.conftest import make_user, session_of
from tests.unit.sockets import receive_until


def test_drift_is_drawn_when_a_node_changes_and_only_then(transactional_db, redis_server, settings):
    from lifecycle_site.dashboard.routing import websocket_urlpatterns

    settings.CHANNEL_LAYERS = {"default": {"BACKEND": "channels.layers.InMemoryChannelLayer"}}
    robot = Robot.objects.create(name="mc-agv", domain_id=54, gateway=Gateway.objects.create(name="cell-mc"))
    node = ManagedNode.objects.create(robot=robot, name="/lidar", alive=True, state_id=sm.ACTIVE,
                                      state_label="active")
    mode = Mode.objects.create(name="mc-mapping", nodes={"/lidar": {"state": "active"}})
    mode.robots.add(robot)
    CurrentMode.objects.create(robot=robot, mode=mode, since=timezone.now())
    stack.write_beat("cell-mc")
    user = make_user("olga-mc", "viewer")
    session = session_of(user)

    async def scenario():
        communicator = WebsocketCommunicator(URLRouter(websocket_urlpatterns), f"/ws/robots/{robot.name}/modes/")
        communicator.scope["user"] = user
        communicator.scope["session"] = session
        assert (await communicator.connect(timeout=5))[0]
        try:
            snapshot = await receive_until(communicator, 'id="modes-live"')
            assert "Every node is as the mode says" in snapshot
            await database_sync_to_async(ManagedNode.objects.filter(pk=node.pk).update)(
                state_id=sm.INACTIVE, state_label="inactive")
            node.state_id = sm.INACTIVE
            await get_channel_layer().group_send(protocol.robot_group(robot.id),
                                                 {"type": "node.state", "node": node_dict(node)})
            live = await receive_until(communicator, 'id="modes-live"')
            assert "1 difference" in live and "drift-state" in live
            for _ in range(3):  # the same again: nothing new to show, nothing sent
                await get_channel_layer().group_send(protocol.robot_group(robot.id),
                                                     {"type": "node.state", "node": node_dict(node)})
            await asyncio.sleep(0.3)
            assert await communicator.receive_nothing(timeout=0.3)
        finally:
            await communicator.disconnect()

    async_to_sync(scenario)()
