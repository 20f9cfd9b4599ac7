"""Telling a new instance of a node's process from the one that ran it (ros_gateway/discovery.py
with the registry), from what the graph lists: a process shutting down removes its node's
endpoints before its name leaves the graph; the next process under that name must still count as
a new instance (and so be recovered), not be taken for the one that left."""
from __future__ import annotations

from ros_gateway import discovery as disc
from ros_gateway.parts import Core
from ros_gateway.registry import NodeRegistry, RobotInfo, StateChanges

P1, P2 = b"\x01\x0f\x78\xfd\x01\x00" + b"\x00" * 6, b"\x01\x0f\x78\xfd\x02\x00" + b"\x00" * 6


def gid(participant: bytes) -> bytes:
    return participant + b"\x00\x00\x01\x03"


class Domain:
    """The graph as the gateway reads it: the endpoints under each node's name."""

    domain_id = 5

    def __init__(self) -> None:
        self.endpoints: dict[str, frozenset] = {}

    def incarnation(self, name: str) -> frozenset:
        return self.endpoints.get(name, frozenset())

    def forget_node(self, name: str, keep: bool = False) -> None:
        pass

    def watch_node(self, name: str) -> None:
        pass


class Records:
    """The audit facts of lost processes (processes.ProcessRecords), counted."""

    def __init__(self) -> None:
        self.losses: list[str] = []

    def lost(self, node, how: str) -> dict:
        self.losses.append(node.name)
        return {}


def test_a_process_whose_endpoints_went_before_its_name_is_followed_by_a_new_instance():
    changes = StateChanges()
    seen = []
    changes.subscribe("test", seen.append)
    registry = NodeRegistry(changes)
    robot = RobotInfo(1, "agv", 5, "", True)
    discovery = disc.Discovery(Core(registry, {}, outbox=None, relay=None, service_timeout=1.0),
                               lambda domain_id: None, forget_parameters=lambda key: None)
    discovery.records = Records()
    domain = Domain()

    domain.endpoints["/lidar"] = frozenset({gid(P1)})
    node = registry.appeared(5, robot, "/lidar", domain.incarnation("/lidar"))
    registry.set_state(node, 3, read=True)  # running, active
    discovery._check_incarnation(domain, node)
    assert node.live == {P1}

    # P1 shuts down: its endpoints go first, its name is still listed for a moment.
    domain.endpoints["/lidar"] = frozenset()
    discovery._check_incarnation(domain, node)
    assert not node.alive and discovery.records.losses == ["/lidar"]  # it left the graph
    # P2 comes up under the name; the first look finds none of its endpoints yet.
    node = registry.appeared(5, robot, "/lidar", domain.incarnation("/lidar"))
    assert node.respawned, "a node seen before, back with no endpoint known: a new instance"
    registry.set_state(node, 1, read=True)
    assert seen[-1].respawned and seen[-1].state_id == 1  # announced (and so recovered) as new
    domain.endpoints["/lidar"] = frozenset({gid(P2)})
    discovery._check_incarnation(domain, node)
    assert node.live == {P2} and not node.respawned  # its endpoints, once listed: nothing more to announce


def test_after_a_process_is_started_here_its_nodes_are_looked_for_more_often_for_a_while(monkeypatch):
    discovery = disc.Discovery(Core(NodeRegistry(StateChanges()), {}, outbox=None, relay=None, service_timeout=1.0),
                               lambda domain_id: None, forget_parameters=lambda key: None)
    now = [100.0]
    monkeypatch.setattr(disc.time, "monotonic", lambda: now[0])
    assert discovery.pause(0.5) == 0.5
    discovery.hurry()
    assert discovery.pause(0.5) == disc.HURRIED_INTERVAL_S
    assert discovery.pause(0.05) == 0.05  # never slower than asked
    now[0] += disc.HURRY_FOR_S + 0.01
    assert discovery.pause(0.5) == 0.5
