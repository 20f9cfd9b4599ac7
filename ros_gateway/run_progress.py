"""A group run's results as its nodes finish: merged over the run's phases, reported to the site
and pushed to the pages at most every PROGRESS_INTERVAL_S."""
from __future__ import annotations

import asyncio
import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ros_gateway.groups import GroupRunner, Run

# A run's progress goes out (push and fact) at most this often, and at its end.
PROGRESS_INTERVAL_S = 0.25


def merged(earlier: dict, later: dict) -> dict:
    """A node's result over two phases of a run: its steps in turn, the later state. Skipped in
    both is skipped; a later phase not run after an earlier one drove the node says so."""
    steps = [*earlier["steps"], *later["steps"]]
    outcome, message = later["outcome"], later["message"]
    if outcome == "skipped" and earlier["outcome"] == "succeeded":
        outcome, message = "succeeded", earlier["message"]
    elif outcome == "not_run" and earlier["steps"]:
        message = f"{message}; left {earlier.get('state', {}).get('label', 'where the first phase took it')}"
    return {**earlier, **later, "steps": steps, "outcome": outcome, "message": message,
            "node_id": later.get("node_id") or earlier.get("node_id"),
            "duration_ms": round(earlier.get("duration_ms", 0.0) + later.get("duration_ms", 0.0), 1)}


class Progress:
    """A run's results as its nodes finish, saved and pushed at most every PROGRESS_INTERVAL_S
    (a 100-node run sends a handful of updates, not a hundred)."""

    def __init__(self, runner: GroupRunner, run: Run, names: list[str], started: str) -> None:
        self.runner, self.run, self.names, self.started = runner, run, names, started
        self.done: dict[str, dict] = {}
        self.fresh_nodes: list[str] = []  # node keys finished since the last push
        self.last_push = 0.0
        self.pending: asyncio.Task | None = None  # the task sending updates, while there are any
        self.waiting = False  # it is in its sleep (safe to cancel)
        self.changed = False  # results finished since the last update

    def results(self) -> list[dict]:
        """Finished nodes' results, in the run's order."""
        return [self.done[name] for name in self.names if name in self.done]

    def failed(self, name: str) -> bool:
        return self.done.get(name, {}).get("outcome") == "failed"

    def finished(self, result: dict) -> None:
        earlier = self.done.get(result["node"])
        self.done[result["node"]] = merged(earlier, result) if earlier else result
        if result.get("node_id"):
            self.fresh_nodes.append(result["node_id"])
        self.changed = True
        if self.pending is None:
            self.pending = asyncio.ensure_future(self._push_while_changed())

    async def _push_while_changed(self) -> None:
        try:
            while self.changed:
                self.waiting = True
                await asyncio.sleep(max(0.0, self.last_push + PROGRESS_INTERVAL_S - time.monotonic()))
                self.waiting, self.changed = False, False
                self.runner.report(self.run, "running", "", self.results(), started=self.started)
                await self.push()
        finally:
            self.waiting = False
            if self.pending is asyncio.current_task():
                self.pending = None

    async def close(self) -> None:
        """Drop an update still waiting its turn, or let one under way finish (so it cannot
        overtake the final one, which follows)."""
        pending, self.pending = self.pending, None
        if pending is not None:
            if self.waiting:
                pending.cancel()
            await asyncio.gather(pending, return_exceptions=True)

    async def push(self, status: str = "running", message: str = "") -> None:
        self.last_push = time.monotonic()
        run = self.run
        # The robot's and the fleet's pages follow every run; a node page only its own node's
        # (always so for a restart or recovery, which are about one node): ``nodes`` names them.
        nodes = list(dict.fromkeys(self.fresh_nodes))
        self.fresh_nodes = []
        await self.runner.relay.publish(
            {"type": "run.progress", "nodes": nodes,
             "run": {"id": run.id, "robot": run.robot.name, "operation": run.operation, "policy": run.policy,
                     "status": status, "message": message, "results": self.results()}},
        )
