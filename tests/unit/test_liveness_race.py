"""A probe of a process that was killed may end after the node came back in a new process
under the same name (its supervisor restarts it at once). The silent old process must not
take the node of the new one with it: the new instance stays alive, and its recovery runs."""
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
