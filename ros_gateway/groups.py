"""Ordered group operations on a robot's nodes, soft restart and automatic recovery.

What Nav2's lifecycle manager does, without its surprises: nodes already where they should
be are skipped, not failed; after a timeout the real state is read again before a node is
called failed; a failure stops the run or not, as the operator chose; every step lands in
the audit log under the run's id, and progress is pushed after every node.
"""
from __future__ import annotations

import asyncio
import logging
import time
import uuid
from datetime import datetime, timezone
from typing import TYPE_CHECKING

from django.db.models import F

from lifecycle_site.fleet.models import GroupRun, ManagedNode
from ros_gateway.lifecycle import NodeUnreachable, read_state
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm
from ros_gateway.store import db

if TYPE_CHECKING:
    from ros_gateway.service import Gateway, LiveNode

log = logging.getLogger(__name__)

# Operation -> (target state, nodes in reverse order?, states the operation leaves alone)
PLANS: dict[str, tuple[int, bool, tuple[int, ...]]] = {
    "bringup": (sm.ACTIVE, False, ()),
    "pause": (sm.INACTIVE, True, (sm.UNCONFIGURED,)),
    "resume": (sm.ACTIVE, False, (sm.UNCONFIGURED,)),
    "reset": (sm.UNCONFIGURED, True, ()),
    "shutdown": (sm.FINALIZED, True, ()),
    "restart": (sm.ACTIVE, False, ()),
}
DESIRED = {"unconfigured": sm.UNCONFIGURED, "inactive": sm.INACTIVE, "active": sm.ACTIVE}
# After a step timed out with the node still inside the transition, how many more timeouts
# to give it to finish before calling it failed.
SETTLE_TIMEOUTS = 3
# Nodes of one tier driven at the same time, at most.
TIER_CONCURRENCY = 8
# A run's progress goes out (push and save) at most this often, and at its end.
PROGRESS_INTERVAL_S = 0.25
# Crash-loop guard: at most this many recoveries of one node within the window.
RECOVERY_LIMIT, RECOVERY_WINDOW_S = 3, 300.0


def _load(run_id: str) -> GroupRun | None:
    return GroupRun.objects.select_related("robot").filter(pk=run_id).first()


def _tiers(robot_id: int, only: list[str]) -> list[list[str]]:
    """The robot's bring-up order as tiers run one after the other: one tier per position
    (nodes sharing a position go together), then every node without a position. Nodes within
    a tier have no order between them. ``only`` narrows the run to those nodes."""
    rows = ManagedNode.objects.filter(robot_id=robot_id).order_by(F("order").asc(nulls_last=True), "name")
    wanted = set(only)
    tiers: dict[int | None, list[str]] = {}
    for name, position in rows.values_list("name", "order"):
        if not only or name in wanted:
            tiers.setdefault(position, []).append(name)
    listed = {name for tier in tiers.values() for name in tier}
    # Named but unknown by now (removed meanwhile): still reported, as "not running".
    missing = [name for name in only if name not in listed]
    return [*tiers.values(), *([missing] if missing else [])]


def _save(run_id: str, **fields) -> None:
    GroupRun.objects.filter(pk=run_id).update(**fields)


def _create_recovery(robot_id: int, node_name: str, target: str, gave_up: str = "") -> str:
    run = GroupRun.objects.create(
        id=uuid.uuid4().hex, robot_id=robot_id, operation=GroupRun.Operation.RECOVER, only_nodes=[node_name],
        source="recovery", status=GroupRun.Status.FAILED if gave_up else GroupRun.Status.QUEUED,
        message=gave_up or f"back to {target}",
    )
    return run.id


class GroupRunner:
    def __init__(self, gateway: "Gateway") -> None:
        self.gateway = gateway
        self.recovering: set[str] = set()  # node keys with a recovery under way
        self.recent_recoveries: dict[str, list[float]] = {}

    async def start(self, run_id: str) -> dict:
        """Accept a recorded run and carry it out in the background."""
        run = await db(_load)(run_id)
        if run is None:
            return {"ok": False, "error": {"code": "not_found", "message": f"There is no run {run_id}."}}
        if run.robot_id not in self.gateway.robots:
            message = f"Robot {run.robot.name} is not watched (disabled or just added); try again in a moment."
            await db(_save)(run_id, status=GroupRun.Status.FAILED, message=message)
            return {"ok": False, "error": {"code": "robot_not_watched", "message": message}}
        self.gateway.spawn(self._execute(run))
        return {"ok": True, "run_id": run_id}

    async def recover(self, node: "LiveNode", desired: str) -> None:
        """Drive a node that came back (after its process was restarted) to its desired state."""
        if node.key in self.recovering:
            return
        now = time.monotonic()
        recent = [t for t in self.recent_recoveries.get(node.key, []) if now - t < RECOVERY_WINDOW_S]
        if len(recent) >= RECOVERY_LIMIT:
            message = (f"gave up: {len(recent)} recoveries in the last {RECOVERY_WINDOW_S / 60:.0f} min "
                       "(the node keeps dying); bring it up by hand once the cause is fixed")
            log.error("not recovering %s:%s: %s", node.robot.name, node.name, message)
            await db(_create_recovery)(node.robot.id, node.name, desired, gave_up=message)
            return
        self.recent_recoveries[node.key] = [*recent, now]
        self.recovering.add(node.key)
        try:
            log.info("recovering %s:%s to %s", node.robot.name, node.name, desired)
            run_id = await db(_create_recovery)(node.robot.id, node.name, desired)
            run = await db(_load)(run_id)
            await self._execute(run, target_override=DESIRED[desired])
        finally:
            self.recovering.discard(node.key)

    async def _execute(self, run: GroupRun, target_override: int | None = None) -> None:
        started = datetime.now(timezone.utc)
        await db(_save)(run.id, status=GroupRun.Status.RUNNING, started=started)
        plan = PLANS.get(run.operation)
        target, reverse, leave_alone = plan if plan else (target_override, False, ())
        if target_override is not None:
            target = target_override
        tiers = await db(_tiers)(run.robot_id, run.only_nodes)
        if reverse:
            tiers = [list(reversed(tier)) for tier in reversed(tiers)]
        names = [name for tier in tiers for name in tier]
        progress = _Progress(self.gateway, run, names)
        limit = asyncio.Semaphore(TIER_CONCURRENCY)
        stopped_by: list[str] = []  # the node whose failure stopped the run

        async def drive(name: str) -> None:
            async with limit:
                if stopped_by:
                    result = {"node": name, "outcome": "not_run", "steps": [],
                              "message": f"not run: the run stopped after {stopped_by[0]} failed"}
                else:
                    node = self.gateway.find_node(run.robot.name, name)
                    try:
                        result = await self._drive_node(run, node, name, target, leave_alone)
                    except Exception as exc:  # a bug or the database: this node fails, the run ends cleanly
                        log.exception("run %s: driving %s failed", run.id, name)
                        result = {"node": name, "node_id": node.key if node else None, "outcome": "failed",
                                  "steps": [], "message": f"the gateway could not drive it ({exc})"}
                    if result["outcome"] == "failed" and run.policy == GroupRun.Policy.STOP and not stopped_by:
                        stopped_by.append(name)
            progress.finished(result)

        for tier in tiers:
            await asyncio.gather(*(drive(name) for name in tier))
        results = progress.results()
        failed = sum(r["outcome"] == "failed" for r in results)
        if not failed:
            status = GroupRun.Status.SUCCEEDED
        elif stopped_by or failed == len(results):
            status = GroupRun.Status.FAILED
        else:
            status = GroupRun.Status.PARTIAL
        summary = ", ".join(f"{sum(r['outcome'] == o for r in results)} {o.replace('_', ' ')}"
                            for o in ("succeeded", "skipped", "failed", "not_run")
                            if any(r["outcome"] == o for r in results))
        await progress.close()
        await db(_save)(run.id, status=status, results=results, finished=datetime.now(timezone.utc),
                        message=summary or "no nodes")
        await progress.push(status=status, message=summary)
        log.info("run %s (%s of %s): %s", run.id, run.operation, run.robot.name, summary)

    async def _drive_node(self, run: GroupRun, node: "LiveNode | None", name: str, target: int,
                          leave_alone: tuple[int, ...]) -> dict:
        result = {"node": name, "node_id": node.key if node else None, "steps": [], "outcome": "succeeded",
                  "message": ""}
        if node is None or not node.alive:
            return {**result, "outcome": "failed", "message": f"{name} is not running"}
        began = time.perf_counter()
        try:
            # Bound everything, waiting for a busy node included: per step a call, re-reads, settling.
            async with asyncio.timeout(run.node_timeout * (4 + SETTLE_TIMEOUTS) * 4 + 5):
                async with node.lock:
                    state = await self._settled_state(node, run.node_timeout)
                    if run.operation == "restart" and state in (sm.INACTIVE, sm.ACTIVE):
                        steps = sm.path(state, sm.UNCONFIGURED) + ["configure", "activate"]
                    elif state in leave_alone:
                        return {**result, "outcome": "skipped", "state": sm.state_dict(state),
                                "message": f"left alone ({sm.state_label(state)})"}
                    else:
                        steps = sm.path(state, target)
                    if steps is None:
                        return {**result, "outcome": "failed", "state": sm.state_dict(state),
                                "message": f"cannot go from {sm.state_label(state)} to {sm.state_label(target)}"
                                + (" (restart its process)" if state == sm.FINALIZED else "")}
                    if not steps:
                        return {**result, "outcome": "skipped", "state": sm.state_dict(state),
                                "message": f"already {sm.state_label(state)}"}
                    for label in steps:
                        step = await self._step(run, node, label, state)
                        state = step["to"]["id"]
                        result["steps"].append(step)
                        if step["outcome"] != "succeeded":
                            result.update(outcome="failed", message=step["message"])
                            break
        except NodeUnreachable as exc:
            result.update(outcome="failed", message=str(exc))
        except TimeoutError:
            result.update(outcome="failed", message="gave up waiting for the node (busy or hung)")
        result["state"] = sm.state_dict(node.state_id)
        result["duration_ms"] = round((time.perf_counter() - began) * 1000, 1)
        return result

    async def _step(self, run: GroupRun, node: "LiveNode", label: str, state: int) -> dict:
        """One transition; ``state`` is the node's state as just read or reached (no re-read)."""
        outcome, record = await self.gateway.driver.transition(
            node, label, run.node_timeout, source=run.source, user_id=run.requested_by_id, run_id=run.id,
            known_state=state if sm.is_primary(state) else None,
        )
        status, message = outcome.outcome, outcome.message
        if status == "timed_out":
            # Nav2 calls this a failure without looking; the node may just have been slow.
            state = await self._settled_state(node, SETTLE_TIMEOUTS * run.node_timeout)
            goal = sm.SUCCESS_GOAL.get(outcome.transition.id) if outcome.transition else None
            if state == goal:
                status, message = "succeeded", f"slow: answered after the timeout, but reached {sm.state_label(state)}"
        return {"transition": label, "outcome": status, "message": message,
                "duration_ms": round(outcome.duration_ms, 1), "record_id": record["id"],
                "to": sm.state_dict(node.state_id)}

    async def _settled_state(self, node: "LiveNode", timeout: float) -> int:
        """The node's real state, waiting (bounded) while it is inside a transition."""
        domain = self.gateway.domains[node.robot.domain_id]
        deadline = time.monotonic() + timeout
        while True:
            state = await read_state(domain, node.name, timeout)
            if sm.is_primary(state) or time.monotonic() >= deadline:
                await self.gateway.set_state(node, state)
                return state
            await asyncio.sleep(0.1)


class _Progress:
    """A run's results as its nodes finish, saved and pushed at most every PROGRESS_INTERVAL_S
    (a 100-node run sends a handful of updates, not a hundred)."""

    def __init__(self, gateway: "Gateway", run: GroupRun, names: list[str]) -> None:
        self.gateway, self.run, self.names = gateway, run, names
        self.done: dict[str, dict] = {}
        self.fresh_nodes: list[str] = []  # node keys finished since the last push
        self.last_push = 0.0
        self.pending: asyncio.Task | None = None  # the task sending updates, while there are any
        self.waiting = False  # it is in its sleep (safe to cancel)
        self.changed = False  # results finished since the last update

    def results(self) -> list[dict]:
        """Finished nodes' results, in the run's order."""
        return [self.done[name] for name in self.names if name in self.done]

    def finished(self, result: dict) -> None:
        self.done[result["node"]] = result
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
                await db(_save)(self.run.id, results=self.results())
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
        # (always so for a restart or recovery, which are about one node).
        node_groups = [protocol.node_group(key) for key in dict.fromkeys(self.fresh_nodes)]
        self.fresh_nodes = []
        await self.gateway.relay.publish(
            [protocol.robot_group(run.robot_id), protocol.FLEET_GROUP, *node_groups],
            {"type": "run.progress", "run": {"id": run.id, "robot": run.robot.name, "operation": run.operation,
                                             "status": status, "message": message, "results": self.results()}},
        )
