"""A group run's progress: a few updates for many nodes, none after the final one."""
from __future__ import annotations

import asyncio
from types import SimpleNamespace

from ros_gateway import run_progress


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
        progress = run_progress.Progress(runner, run, names, "2026-01-01T00:00:00+00:00")
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
    both = run_progress.merged(down, up)
    assert [s["transition"] for s in both["steps"]] == ["deactivate", "cleanup", "configure", "activate"]
    assert (both["outcome"], both["state"]["label"], both["duration_ms"]) == ("succeeded", "active", 22.5)
    already = {**down, "outcome": "skipped", "message": "already unconfigured", "steps": []}
    assert run_progress.merged(already, up)["outcome"] == "succeeded"
    assert run_progress.merged(already, {**up, "outcome": "skipped", "steps": []})["outcome"] == "skipped"
    stopped = {"node": "/a", "outcome": "not_run", "steps": [], "message": "not run: the run stopped after /b failed"}
    left = run_progress.merged(down, stopped)
    assert left["outcome"] == "not_run" and left["state"]["label"] == "unconfigured" and left["node_id"] == "agv.a"
    assert left["message"] == "not run: the run stopped after /b failed; left unconfigured"
