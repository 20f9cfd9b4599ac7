"""The gateway keeping desired states against other tools (ros_gateway/desired_keeper.py), its
decisions on their own: a change by another tool undone after the grace; a fight given up after
FIGHT_LIMIT undos, said once; resumed only by a newer "resumed" in the site's config; a node whose
policy is not "enforce" never driven. (On real nodes, against a competing process:
tests/integration/test_keep_desired.py.)"""
from __future__ import annotations

import asyncio

import pytest

from ros_gateway import desired_keeper
from ros_gateway.desired_keeper import FIGHT_LIMIT, DesiredKeeper
from ros_gateway.registry import LiveNode, NodeRegistry, NodeSettings, RobotInfo, StateChanges
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm

ROBOT = RobotInfo(id=1, name="agv", domain_id=5, namespace="")


class Runner:
    """Drives a node at once to the phase's target; keeps what it was asked and what it reported."""

    def __init__(self) -> None:
        self.outbox = self
        self.runs: list[tuple[str, int]] = []
        self.facts: list[dict] = []
        self.node: LiveNode | None = None

    def report(self, run, status, message, results, **spec) -> dict:
        return {}

    async def execute(self, run, phases) -> None:
        self.runs.append((run.tiers[0][0], phases[0].target))
        self.node.state_id = phases[0].target

    def emit(self, kind: str, **fields) -> dict:
        self.facts.append({"type": kind, **fields})
        return self.facts[-1]


@pytest.fixture
def kept(monkeypatch):
    monkeypatch.setattr(desired_keeper, "GRACE_S", 0.0)
    registry = NodeRegistry(StateChanges())
    registry.robots[1] = ROBOT
    node = LiveNode(robot=ROBOT, name="/camera", alive=True, state_id=sm.INACTIVE)
    registry.nodes[(5, node.name)] = node
    runner = Runner()
    runner.node = node
    keeper = DesiredKeeper(runner, registry)

    def settings(**fields) -> None:
        registry.settings[1] = {node.name: NodeSettings(desired_state="inactive", **fields)}

    settings(keep="enforce")
    return keeper, runner, node, settings


def moved(keeper: DesiredKeeper, node: LiveNode, state: int = sm.ACTIVE) -> None:
    """Another tool moves the node; the keeper hears of it (and its grace, 0 here, passes)."""
    async def main() -> None:
        node.state_id = state
        keeper.on_external(node)
        for _ in range(5):
            await asyncio.sleep(0)

    asyncio.run(main())


def test_a_change_by_another_tool_is_undone_and_a_fight_is_given_up_once(kept):
    keeper, runner, node, _ = kept
    for _ in range(FIGHT_LIMIT):
        moved(keeper, node)
        assert node.state_id == sm.INACTIVE
    assert runner.runs == [("/camera", sm.INACTIVE)] * FIGHT_LIMIT and runner.facts == []
    moved(keeper, node)  # once more: another manager is at work
    assert node.state_id == sm.ACTIVE and len(runner.runs) == FIGHT_LIMIT
    assert [f["type"] for f in runner.facts] == [protocol.ENFORCEMENT_STOPPED]
    assert runner.facts[0]["message"].startswith(f"another manager keeps changing /camera (moved away from its "
                                                 f"desired state {FIGHT_LIMIT + 1} times in 10 min")
    moved(keeper, node, sm.INACTIVE)
    moved(keeper, node)
    assert len(runner.runs) == FIGHT_LIMIT and len(runner.facts) == 1  # left alone: nothing sent, said once


def test_only_a_newer_resume_from_the_site_ends_the_pause(kept):
    keeper, runner, node, settings = kept
    for _ in range(FIGHT_LIMIT + 1):
        moved(keeper, node)
    settings(keep="enforce")  # the config from before the site heard of the fight
    keeper.on_settings()
    settings(keep=protocol.KEEP_PAUSED)
    keeper.on_settings()
    moved(keeper, node)
    assert len(runner.runs) == FIGHT_LIMIT

    async def resume() -> None:
        settings(keep="enforce", resumed="2026-11-26T21:00:00+00:00")
        keeper.on_settings()  # the node is taken back at once (it was left active)
        for _ in range(5):
            await asyncio.sleep(0)

    asyncio.run(resume())
    assert node.state_id == sm.INACTIVE and len(runner.runs) == FIGHT_LIMIT + 1
    moved(keeper, node)
    assert node.state_id == sm.INACTIVE and len(runner.runs) == FIGHT_LIMIT + 2  # kept again, counted afresh


@pytest.mark.parametrize("policy", ["off", "alert", protocol.KEEP_PAUSED])
def test_a_node_not_enforced_is_never_driven(kept, policy):
    keeper, runner, node, settings = kept
    settings(keep=policy)
    moved(keeper, node)
    assert runner.runs == [] and node.state_id == sm.ACTIVE


def test_a_change_the_tool_undid_itself_within_the_grace_is_not_counted(kept):
    keeper, runner, node, _ = kept

    async def main() -> None:
        node.state_id = sm.ACTIVE
        keeper.on_external(node)
        node.state_id = sm.INACTIVE  # back before the grace ended
        for _ in range(5):
            await asyncio.sleep(0)

    asyncio.run(main())
    assert runner.runs == [] and keeper.undone == {}


def test_a_change_made_while_the_last_one_was_being_undone_is_not_lost(kept):
    """Another manager may move the node again while the gateway's run is still under way (its
    event comes before the run ends): it is looked at again once the run ended."""
    keeper, runner, node, _ = kept
    execute = runner.execute

    async def slow_execute(run, phases) -> None:
        await execute(run, phases)
        node.state_id = sm.ACTIVE  # moved again before the run's end was known
        keeper.on_external(node)

    runner.execute = slow_execute

    async def main() -> None:
        node.state_id = sm.ACTIVE
        keeper.on_external(node)
        for _ in range(20):
            await asyncio.sleep(0)

    asyncio.run(main())
    assert len(runner.runs) >= 2  # the second change was undone too (and so on, up to the fight limit)


def test_a_state_put_back_by_a_late_reply_is_read_from_the_node(kept):
    """The reply to the gateway's own undo, handled after the other tool's next transition events,
    leaves the registry saying "inactive" while the node is active (seen once under load): the
    node's state is read before the keeper decides there is nothing to undo."""
    keeper, runner, node, _ = kept
    really = {"state": sm.ACTIVE}
    reads: list[str] = []

    async def read_state(read_node: LiveNode) -> bool:
        reads.append(read_node.name)
        read_node.state_id = really["state"]
        return True

    keeper.read_state = read_state

    async def main() -> None:
        node.state_id = sm.INACTIVE  # what the late reply put back
        keeper.on_external(node)
        for _ in range(10):
            await asyncio.sleep(0)

    asyncio.run(main())
    assert reads == ["/camera"] and runner.runs == [("/camera", sm.INACTIVE)]
    really["state"] = sm.INACTIVE  # really in its desired state: left alone, not counted
    asyncio.run(main())
    assert reads == ["/camera"] * 2 and len(runner.runs) == 1 and len(keeper.undone[node.key]) == 1
