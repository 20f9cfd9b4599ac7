"""What the gateway records of /parameter_events (ros_gateway/param_keeper.py): a change made by
another tool is audited as ``external``; a node declaring its parameters as it starts is not a
change by anyone, whenever its events come (before or after the gateway found the node)."""
from __future__ import annotations

import asyncio

from rcl_interfaces.msg import Parameter, ParameterEvent, ParameterType, ParameterValue

from ros_gateway.param_keeper import ParameterKeeper
from ros_gateway.registry import LiveNode, NodeRegistry, RobotInfo, StateChanges

DOMAIN = 5
ROBOT = RobotInfo(id=1, name="agv", domain_id=DOMAIN, namespace="")
NODE_KEY = LiveNode(robot=ROBOT, name="/flaky_node").key


class Outbox:
    def __init__(self) -> None:
        self.facts: list[dict] = []

    def emit(self, kind: str, **fields) -> dict:
        self.facts.append({"type": kind, **fields})
        return self.facts[-1]


class Relay:
    def __init__(self) -> None:
        self.published: list[dict] = []

    async def publish(self, message: dict) -> None:
        self.published.append(message)


def parameter(name: str, value) -> Parameter:
    if isinstance(value, bool):
        return Parameter(name=name, value=ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=value))
    return Parameter(name=name, value=ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=value))


def event(new=(), changed=()) -> ParameterEvent:
    return ParameterEvent(node="/flaky_node", new_parameters=[parameter(*p) for p in new],
                          changed_parameters=[parameter(*p) for p in changed])


def keeper_with_node() -> tuple[ParameterKeeper, Outbox, Relay]:
    registry = NodeRegistry(StateChanges())
    registry.nodes[(DOMAIN, "/flaky_node")] = LiveNode(robot=ROBOT, name="/flaky_node", alive=True)
    outbox, relay = Outbox(), Relay()
    return ParameterKeeper({}, registry, outbox, relay), outbox, relay


def run(body) -> None:
    async def main() -> None:
        body()
        await asyncio.sleep(0)  # the live pushes are tasks

    asyncio.run(main())


def test_a_node_declaring_its_parameters_after_it_was_found_makes_no_record():
    keeper, outbox, relay = keeper_with_node()
    run(lambda: keeper.on_event(DOMAIN, event(new=[("use_sim_time", False), ("failure_mode", "fail_configure")])))
    assert outbox.facts == []
    assert relay.published == []


def test_a_change_by_another_tool_is_recorded_as_external_with_its_old_value():
    keeper, outbox, relay = keeper_with_node()
    keeper.cache[NODE_KEY] = {"failure_mode": {"name": "failure_mode", "value": "fail_configure"}}
    run(lambda: keeper.on_event(DOMAIN, event(changed=[("failure_mode", "none")])))
    assert [(f["name"], f["old"], f["new"], f["source"]) for f in outbox.facts] == [
        ("failure_mode", "fail_configure", "none", "external")]
    assert relay.published[0]["changes"] == [{"name": "failure_mode", "old": "fail_configure", "new": "none"}]


def test_a_change_seen_before_the_parameters_were_ever_listed_is_still_recorded():
    keeper, outbox, _ = keeper_with_node()
    run(lambda: keeper.on_event(DOMAIN, event(changed=[("failure_mode", "none")])))
    assert [(f["name"], f["old"], f["new"]) for f in outbox.facts] == [("failure_mode", None, "none")]


def test_a_value_set_on_an_undeclared_name_of_a_listed_node_is_recorded():
    """A node that allows undeclared parameters: ``ros2 param set`` on a new name comes as a new
    parameter; its listing was read, so it is a change, not the node's start."""
    keeper, outbox, _ = keeper_with_node()
    keeper.cache[NODE_KEY] = {"failure_mode": {"name": "failure_mode", "value": "none"}}
    run(lambda: keeper.on_event(DOMAIN, event(new=[("speed_limit", "slow")])))
    assert [(f["name"], f["old"], f["new"]) for f in outbox.facts] == [("speed_limit", None, "slow")]
