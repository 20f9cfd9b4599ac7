"""Races around a node whose process was killed and restarted at once (by its supervisor):
a probe of the old process may end after the node came back in the new one, and the new one
may answer only after liveness called it unreachable (so a new process is not probed before
it is heard from, for a grace). Either way the new instance ends up alive and announced once,
so that its recovery runs (and does not start while it is away)."""
from __future__ import annotations

import asyncio
from types import SimpleNamespace

from ros_gateway import liveness as lv
from ros_gateway.lifecycle import NodeUnreachable
from ros_gateway.registry import LiveNode, NodeRegistry, RobotInfo, StateChanges

OLD, NEW = b"old-process!", b"new-process!"


def probe_while(monkeypatch, replace: bool) -> tuple[LiveNode, lv.Liveness]:
    registry = NodeRegistry(StateChanges())
    robot = RobotInfo(1, "agv", 5, "", True)
    node = LiveNode(robot, "/camera_driver", alive=True, live=frozenset({OLD}), incarnation=frozenset({OLD}))
    registry.nodes[(5, node.name)] = node
    liveness = lv.Liveness(registry, {5: SimpleNamespace(domain_id=5)}, interval=1.0, timeout=0.01)

    async def silent(domain, name, timeout):
        await asyncio.sleep(0)
        if replace:  # meanwhile discovery saw the new process and called the node alive again
            node.live = node.incarnation = frozenset({NEW})
        raise NodeUnreachable("no answer")

    monkeypatch.setattr(lv, "read_state", silent)
    asyncio.run(liveness._probe(lv.process_of(5, node.name, node.live), [node]))
    return node, liveness


def test_a_silent_process_makes_its_nodes_unreachable(monkeypatch):
    node, liveness = probe_while(monkeypatch, replace=False)
    assert not node.alive and node.gone_reason == lv.UNREACHABLE
    assert (5, OLD) in liveness.unreachable


def test_a_node_that_came_back_in_a_new_process_stays_alive_when_the_old_one_is_silent(monkeypatch):
    node, liveness = probe_while(monkeypatch, replace=True)
    assert node.alive and node.gone_reason == ""
    assert not liveness.unreachable


def test_a_new_instance_read_while_the_node_is_called_gone_is_announced_once_it_is_back():
    """The state of a restarted node may be read just after liveness called it unreachable (its
    new process answered late): recovery must wait for the node to be back, not start and fail
    at once, and must not be forgotten."""
    registry = NodeRegistry(StateChanges())
    announced: list[bool] = []
    registry.changes.subscribe("test", lambda change: announced.append(change.respawned)
                               if change.kind == "state" else None)
    robot = RobotInfo(1, "agv", 5, "", True)
    node = registry.appeared(5, robot, "/camera_driver", frozenset({OLD}))
    registry.set_state(node, 3, read=True)  # active
    node.respawned = True  # discovery saw a new process under the name
    registry.vanished(node, reason=lv.UNREACHABLE)
    registry.set_state(node, 1, read=True)  # unconfigured: read while it is called gone
    assert announced == [False, False] and node.respawned
    registry.appeared(5, robot, "/camera_driver", frozenset({NEW}))
    registry.set_state(node, 1, read=True)
    assert announced == [False, False, True] and not node.respawned


def test_a_new_process_not_heard_from_yet_is_probed_only_after_a_grace(monkeypatch):
    """DDS needs a moment to match a new process's services both ways; probed at once, a node
    that just came back would be called unreachable although it is fine."""
    registry = NodeRegistry(StateChanges())
    robot = RobotInfo(1, "agv", 5, "", True)
    node = registry.appeared(5, robot, "/camera_driver", frozenset({NEW}))
    node.state_id = 3  # as its old process left it (active); the new one's not read yet
    liveness = lv.Liveness(registry, {5: SimpleNamespace(domain_id=5)}, interval=1.0, timeout=0.01)
    probed: list[str] = []

    async def answering(domain, name, timeout):
        probed.append(name)
        return 1

    monkeypatch.setattr(lv, "read_state", answering)

    async def one_pass() -> None:
        await liveness.probe()
        await asyncio.sleep(0.01)  # the probes it started

    asyncio.run(one_pass())
    assert probed == []  # new, its state not read yet
    liveness._first_seen[(5, NEW)] -= lv.NEW_PROCESS_GRACE_S
    asyncio.run(one_pass())
    assert probed == ["/camera_driver"]  # the grace is over
    other = registry.appeared(5, robot, "/lidar_driver", frozenset({OLD}))
    other.state_id, other.state_read = 3, True  # heard from: probed at once
    asyncio.run(one_pass())
    assert probed.count("/lidar_driver") == 1
