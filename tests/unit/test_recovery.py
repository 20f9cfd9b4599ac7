"""Automatic recovery (ros_gateway/recovery.py): the crash-loop guard, restarts asked for that do
not count towards it, a node back again while its recovery runs, and the nodes of one restarted
process gathered into one run in the robot's order."""
from __future__ import annotations

import asyncio

from ros_gateway import groups
from ros_gateway.recovery import Recovery


class _Outbox:
    def __init__(self) -> None:
        self.facts: list[dict] = []

    def emit(self, kind: str, **fields) -> dict:
        self.facts.append({"type": kind, **fields})
        return self.facts[-1]


def _recovering_runner():
    """A GroupRunner whose runs only count (the transitions themselves are the node driver's)."""
    from ros_gateway.parts import Core
    from ros_gateway.registry import LiveNode, NodeRegistry, RobotInfo, StateChanges

    registry = NodeRegistry(StateChanges(report=lambda change: {}))
    robot = RobotInfo(1, "agv", 21, "", auto_recover=True)
    node = LiveNode(robot=robot, name="/lidar", alive=True, process="drivers")
    registry.nodes[(21, "/lidar")] = node
    outbox = _Outbox()
    runner = groups.GroupRunner(Core(registry, {}, outbox, None, 5.0), driver=None)
    executed: list[str] = []

    async def execute(run, phases=None) -> None:
        executed.append(run.id)
        runs.append(run)

    runs: list = []
    runner.execute = execute
    recovery = Recovery(runner)
    recovery.runs = runs
    return recovery, node, outbox, executed


def test_a_node_that_keeps_coming_back_is_given_up_after_three_recoveries():
    runner, node, outbox, executed = _recovering_runner()

    async def main() -> None:
        for _ in range(4):
            await runner.recover(node, "active")

    asyncio.run(main())
    assert len(executed) == 3
    assert "gave up: 3 recoveries in the last 5 min" in outbox.facts[-1]["message"]


def test_restarts_someone_asked_for_are_not_a_crash_loop():
    runner, node, outbox, executed = _recovering_runner()

    async def main() -> None:
        for _ in range(2):  # two crashes
            await runner.recover(node, "active")
        for _ in range(4):  # then four restarts of its process by an operator, each recovered
            runner.forgive("agv", "drivers")
            await runner.recover(node, "active")
        runner.forgiven.clear()  # and once that is long past, a crash counts again, from none
        for _ in range(3):
            await runner.recover(node, "active")

    asyncio.run(main())
    assert len(executed) == 2 + 4 + 3
    assert not any("gave up" in fact.get("message", "") for fact in outbox.facts)


def test_a_node_back_again_while_its_recovery_runs_is_recovered_again():
    runner, node, outbox, executed = _recovering_runner()
    release = asyncio.Event()

    async def slow(run, phases=None) -> None:
        executed.append(run.id)
        if len(executed) == 1:
            await release.wait()

    runner.runner.execute = slow

    async def main() -> None:
        first = asyncio.ensure_future(runner.recover(node, "active"))
        await asyncio.sleep(0)
        await runner.recover(node, "inactive")  # restarted again meanwhile: remembered
        release.set()
        await first
        for _ in range(20):
            await asyncio.sleep(0.01)

    asyncio.run(main())
    assert len(executed) == 2 and outbox.facts[-1]["message"] == "back to inactive"


def test_the_nodes_of_one_restarted_process_are_recovered_as_one_run_in_the_robots_order():
    from ros_gateway.registry import LiveNode, NodeSettings, StateChange

    runner, node, outbox, executed = _recovering_runner()
    robot = node.robot
    registry = runner.registry
    names = ["/planner", "/camera", "/lidar", "/base"]
    orders = {"/base": 1, "/lidar": 2, "/camera": 2}  # the planner has no position: last
    registry.settings[robot.id] = {n: NodeSettings(order=orders.get(n), desired_state="active") for n in names}
    nodes = [registry.nodes.get((21, n)) or LiveNode(robot=robot, name=n, alive=True) for n in names]

    async def main() -> None:
        for back in nodes:  # their states read one after the other, as discovery does
            runner.on_change(StateChange(back, "state", 1, respawned=True))
            await asyncio.sleep(0.02)
        runner.on_change(StateChange(nodes[0], "state", 1, respawned=True))  # the same node twice: once
        for _ in range(50):
            await asyncio.sleep(0.02)
            if executed:
                break

    asyncio.run(main())
    (run,) = runner.runs
    assert run.tiers == [["/base"], ["/camera", "/lidar"], ["/planner"]]
    assert run.source == "recovery" and run.operation == "recover"
    queued = [f for f in outbox.facts if f.get("status") == "queued"]
    assert len(queued) == 1 and queued[0]["only_nodes"] == ["/base", "/camera", "/lidar", "/planner"]
    assert queued[0]["policy"] == "continue"  # one node failing does not keep the others down
