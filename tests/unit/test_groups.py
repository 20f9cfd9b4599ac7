"""A group run's progress: a few updates for many nodes, none after the final one."""
from __future__ import annotations

import asyncio
from types import SimpleNamespace

from ros_gateway import groups


class Relay:
    def __init__(self) -> None:
        self.messages: list[dict] = []
        self.calls = 0

    async def publish(self, message: dict) -> None:
        # A Redis round trip; the first one slow, as after a reconnect.
        self.calls += 1
        await asyncio.sleep(0.05 if self.calls == 1 else 0.005)
        self.messages.append(message["run"])


def _run_progress(finish_gaps: list[float]) -> list[dict]:
    saved: list[list[dict]] = []
    relay = Relay()
    runner = SimpleNamespace(relay=relay, _report=lambda run, status, message, results, **_: saved.append(results))
    run = SimpleNamespace(id="r1", robot=SimpleNamespace(id=1, name="agv"), operation="bringup", policy="stop")
    names = [f"/n{i:03d}" for i in range(len(finish_gaps))]

    async def main() -> None:
        progress = groups._Progress(runner, run, names, "2026-01-01T00:00:00+00:00")
        for name, gap in zip(reversed(names), finish_gaps, strict=True):  # finishing out of order
            await asyncio.sleep(gap)
            progress.finished({"node": name, "node_id": f"agv.{name[1:]}", "outcome": "succeeded"})
        await progress.close()
        await progress.push(status="succeeded", message="done")

    asyncio.run(main())
    return relay.messages


def test_many_nodes_finishing_at_once_make_a_few_updates_in_the_runs_order():
    messages = _run_progress([0.004] * 100)  # 100 nodes in ~0.4 s
    assert len(messages) <= 5, len(messages)
    assert messages[-1]["status"] == "succeeded"
    assert [r["node"] for r in messages[-1]["results"]] == [f"/n{i:03d}" for i in range(100)]
    assert all(m["status"] == "running" for m in messages[:-1])


def test_the_final_update_comes_last_whenever_the_last_node_finishes():
    # At once, during the first (slow) update, just before, at and after the next update's turn.
    for gap in (0.0, 0.01, 0.25, 0.255, 0.26):
        messages = _run_progress([0.0, gap])
        assert messages[-1]["status"] == "succeeded", (gap, messages)
        assert len(messages[-1]["results"]) == 2


def test_a_node_over_two_phases_has_one_result_with_all_its_steps():
    down = {"node": "/a", "node_id": "agv.a", "outcome": "succeeded", "message": "", "duration_ms": 10.0,
            "steps": [{"transition": "deactivate"}, {"transition": "cleanup"}],
            "state": {"id": 1, "label": "unconfigured"}}
    up = {"node": "/a", "node_id": "agv.a", "outcome": "succeeded", "message": "", "duration_ms": 12.5,
          "steps": [{"transition": "configure"}, {"transition": "activate"}], "state": {"id": 3, "label": "active"}}
    both = groups.merged(down, up)
    assert [s["transition"] for s in both["steps"]] == ["deactivate", "cleanup", "configure", "activate"]
    assert (both["outcome"], both["state"]["label"], both["duration_ms"]) == ("succeeded", "active", 22.5)
    already = {**down, "outcome": "skipped", "message": "already unconfigured", "steps": []}
    assert groups.merged(already, up)["outcome"] == "succeeded"
    assert groups.merged(already, {**up, "outcome": "skipped", "steps": []})["outcome"] == "skipped"
    stopped = {"node": "/a", "outcome": "not_run", "steps": [], "message": "not run: the run stopped after /b failed"}
    left = groups.merged(down, stopped)
    assert left["outcome"] == "not_run" and left["state"]["label"] == "unconfigured" and left["node_id"] == "agv.a"
    assert left["message"] == "not run: the run stopped after /b failed; left unconfigured"


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

    runner._execute = execute
    return runner, node, outbox, executed


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

    runner._execute = slow

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
