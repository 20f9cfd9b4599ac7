"""The gateway's registry (ros_gateway/registry.py): which robot owns a node, and the one stream
of state changes its listeners see, in order, once per change."""
from __future__ import annotations

from ros_gateway.registry import NodeRegistry, RobotInfo, StateChanges
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm

GID_A, GID_B = bytes(range(12)) + b"\0" * 12, bytes(range(1, 13)) + b"\0" * 12


def registry_with(*robots: RobotInfo) -> tuple[NodeRegistry, list[tuple[str, str, int, bool]]]:
    changes = StateChanges()
    seen: list[tuple[str, str, int, bool]] = []
    changes.subscribe("record", lambda c: seen.append((c.kind, c.node.name, c.state_id, c.respawned)))
    registry = NodeRegistry(changes)
    registry.robots = {r.id: r for r in robots}
    return registry, seen


def test_a_node_belongs_to_the_robot_with_the_longest_matching_namespace_in_its_domain():
    whole = RobotInfo(1, "agv-1", 20, "")
    arm = RobotInfo(2, "agv-1-arm", 20, "/arm")
    other = RobotInfo(3, "agv-2", 21, "")
    registry, _ = registry_with(whole, arm, other)
    assert registry.robot_for(20, "/arm/gripper") == arm
    assert registry.robot_for(20, "/armrest") == whole  # a namespace is a path, not a prefix of letters
    assert registry.robot_for(21, "/arm/gripper") == other
    assert registry.robot_for(22, "/lidar") is None


def test_changes_reach_the_listeners_in_order_once_each_and_a_failing_listener_stops_none():
    robot = RobotInfo(1, "agv-1", 20, "")
    registry, seen = registry_with(robot)
    calls: list[str] = []
    registry.changes.subscribe("broken", lambda c: 1 / 0)
    registry.changes.subscribe("after", lambda c: calls.append(c.kind))
    node = registry.appeared(20, robot, "/lidar", frozenset({GID_A}))
    assert registry.set_state(node, sm.INACTIVE) is not None
    assert registry.set_state(node, sm.INACTIVE) is None  # no news, no change
    registry.vanished(node, protocol.PROCESS_LOST, ended=True)
    assert seen == [("seen", "/lidar", sm.UNKNOWN, False), ("state", "/lidar", sm.INACTIVE, False),
                    ("gone", "/lidar", sm.INACTIVE, False)]
    assert calls == ["seen", "state", "gone"]
    assert (node.alive, node.gone_reason, node.process_status) == (False, protocol.PROCESS_LOST, "lost")
    assert registry.find("agv-1", "/lidar") is node and registry.alive_count() == 0


def test_a_new_process_under_the_same_name_is_announced_once_by_its_first_read_state():
    robot = RobotInfo(1, "agv-1", 20, "")
    registry, seen = registry_with(robot)
    node = registry.appeared(20, robot, "/lidar", frozenset({GID_A}))
    registry.set_state(node, sm.ACTIVE, read=True)
    registry.vanished(node, protocol.PROCESS_LOST, ended=True)
    registry.appeared(20, robot, "/lidar", frozenset({GID_B}))  # another process
    seen.clear()
    change = registry.set_state(node, sm.UNCONFIGURED, read=True)
    assert change is not None and change.respawned and node.process_status == "restarted"
    assert registry.set_state(node, sm.UNCONFIGURED, read=True) is None  # announced once
    assert seen == [("state", "/lidar", sm.UNCONFIGURED, True)]


def test_dropping_a_robot_forgets_only_its_nodes():
    one, two = RobotInfo(1, "agv-1", 20, ""), RobotInfo(2, "agv-2", 21, "")
    registry, _ = registry_with(one, two)
    registry.appeared(20, one, "/lidar", frozenset({GID_A}))
    registry.appeared(21, two, "/lidar", frozenset({GID_B}))
    dropped = registry.drop_robot(1)
    assert [(domain, node.robot.name) for domain, node in dropped] == [(20, "agv-1")]
    assert [n.robot.name for n in registry.nodes.values()] == ["agv-2"]


def test_a_change_is_reported_first_and_its_fact_kept_for_the_listeners():
    robot = RobotInfo(1, "agv-1", 20, "")
    order: list[str] = []

    def report(change):
        order.append("report")
        return {"type": protocol.NODE_STATE, "node": change.node.name, "state_id": change.state_id}

    registry = NodeRegistry(StateChanges(report=report))
    registry.changes.subscribe("push", lambda c: order.append(f"push saw {c.fact['type']}"))
    node = registry.appeared(20, robot, "/lidar", frozenset({GID_A}))
    change = registry.set_state(node, sm.ACTIVE)
    assert change.fact == {"type": protocol.NODE_STATE, "node": "/lidar", "state_id": sm.ACTIVE}
    assert order == ["report", f"push saw {protocol.NODE_STATE}"] * 2
