"""Ordered group operations on a robot's nodes and soft restart (automatic recovery, which
runs its own through this module: recovery.py).

What Nav2's lifecycle manager does, without its surprises: nodes already where they should
be are skipped, not failed; after a timeout the real state is read again before a node is
called failed; a failure stops the run or not, as the operator chose; every step lands in
the audit log under the run's id, and progress is pushed after every node. A run the site
has ended meanwhile (verdicts.py) takes no further step.
"""
from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import TYPE_CHECKING, Any

from ros_gateway import mode_plan
from ros_gateway.lifecycle import NodeUnreachable, read_state
from ros_gateway.node_driver import NodeDriver
from ros_gateway.parts import Core
from ros_gateway.registry import LiveNode, NodeRegistry, RobotInfo
from ros_gateway.run_progress import Progress
from ros_gateway.shared import operations, protocol
from ros_gateway.shared import state_machine as sm
from ros_gateway.shared.operations import Phase
from ros_gateway.tasks import spawn
from ros_gateway.verdicts import RunVerdict

if TYPE_CHECKING:
    from ros_gateway.param_keeper import ParameterKeeper

log = logging.getLogger(__name__)

# After a step timed out with the node still inside the transition, how many more timeouts
# to give it to finish before calling it failed.
SETTLE_TIMEOUTS = 3
# Nodes of one tier driven at the same time, at most.
TIER_CONCURRENCY = 16
MAX_NODE_TIMEOUT_S = 60.0


class BadRun(ValueError):
    """The site's description of a run cannot be carried out; the message says why."""


@dataclass
class Run:
    """A group run as the site described it (or as recovery made it)."""

    id: str
    robot: RobotInfo
    operation: str
    policy: str = "stop"
    node_timeout: float = 5.0
    tiers: list[list[str]] = field(default_factory=list)
    source: str = "api"
    user_id: int | None = None
    # A mode's run: each node's target (None: left alone) and the parameters set before it is activated.
    targets: dict[str, int | None] = field(default_factory=dict)
    parameters: dict[str, dict[str, Any]] = field(default_factory=dict)

    @classmethod
    def from_spec(cls, spec: object, registry: NodeRegistry) -> "Run":
        if not isinstance(spec, dict):
            raise BadRun("The run is missing from the command.")
        robot = registry.robot_named(str(spec.get("robot", "")))
        if robot is None:
            raise BadRun(f"Robot {spec.get('robot')!r} is not watched (disabled or just added); try again in a moment.")
        operation = spec.get("operation")
        known = operations.get(operation)
        if known is None or known.scope == operations.GATEWAY:
            raise BadRun(f"{operation!r} is not an operation this gateway knows.")
        tiers = spec.get("tiers")
        if not isinstance(tiers, list) or not all(isinstance(t, list) and all(isinstance(n, str) for n in t)
                                                  for t in tiers):
            raise BadRun("The run's node order (tiers) must be a list of lists of node names.")
        try:
            timeout = float(spec.get("node_timeout", 5.0))
        except (TypeError, ValueError):
            raise BadRun("node_timeout must be a number of seconds.") from None
        if not 0 < timeout <= MAX_NODE_TIMEOUT_S:
            raise BadRun(f"node_timeout must be more than 0 and at most {MAX_NODE_TIMEOUT_S:g} s.")
        targets: dict[str, int | None] = {}
        parameters: dict[str, dict[str, Any]] = {}
        if known.scope == operations.MODE:
            try:
                targets, parameters = mode_plan.parse(spec, [name for tier in tiers for name in tier])
            except mode_plan.BadPlan as exc:
                raise BadRun(str(exc)) from None
        user_id = spec.get("user_id")
        return cls(id=str(spec.get("id") or protocol.new_id()), robot=robot, operation=operation,
                   policy="continue" if spec.get("policy") == "continue" else "stop", node_timeout=timeout,
                   tiers=tiers, source=str(spec.get("source") or "api"),
                   user_id=user_id if isinstance(user_id, int) else None, targets=targets, parameters=parameters)


class GroupRunner:
    def __init__(self, core: Core, driver: NodeDriver, params: ParameterKeeper | None = None) -> None:
        self.domains, self.registry, self.driver, self.params = core.domains, core.registry, driver, params
        self.outbox, self.relay = core.outbox, core.relay

    def start(self, spec: object) -> dict:
        """Accept a run the site recorded and carry it out in the background."""
        try:
            run = Run.from_spec(spec, self.registry)
        except BadRun as exc:
            return {"ok": False, "error": {"code": "bad_run", "message": str(exc)}}
        spawn(self.execute(run))
        return {"ok": True, "run_id": run.id}

    def report(self, run: Run, status: str, message: str, results: list[dict], *, started: str | None = None,
                finished: bool = False, **spec) -> dict:
        """A run fact for the site (``spec`` for runs the gateway starts itself)."""
        return self.outbox.emit(
            protocol.RUN, run_id=run.id, robot=run.robot.name, status=status, message=message, results=results,
            started=started, finished=datetime.now(timezone.utc).isoformat() if finished else None, **spec,
        )

    async def execute(self, run: Run, phases: tuple[Phase, ...] | None = None) -> None:
        """Drive the run's nodes through its operation's phases (``phases`` for a recovery, whose
        target is the node's desired state): each phase goes through every tier, in the robot's
        order or in reverse, before the next phase begins."""
        started = datetime.now(timezone.utc).isoformat()
        self.report(run, "running", "", [], started=started)
        if phases is None:
            phases = operations.BY_NAME[run.operation].phases
        # Results in the order of the last phase (the one that leaves the nodes where they end).
        last_reversed = bool(phases) and phases[-1].reverse
        names = [name for tier in run.tiers for name in tier]
        progress = Progress(self, run, names[::-1] if last_reversed else names, started)
        limit = asyncio.Semaphore(TIER_CONCURRENCY)
        stopped_by: list[str] = []  # the node whose failure stopped the run
        verdict = RunVerdict(self.relay, run.id)

        async def drive(name: str, phase: Phase, stopped: bool) -> None:
            if progress.failed(name):
                return  # failed in an earlier phase: its result stands
            async with limit:
                if verdict.ended:
                    result = {"node": name, "outcome": "not_run", "steps": [], "message": f"not run: {verdict.ended}"}
                elif stopped:
                    result = {"node": name, "outcome": "not_run", "steps": [],
                              "message": f"not run: the run stopped after {stopped_by[0]} failed"}
                else:
                    node = self.registry.find(run.robot.name, name)
                    try:
                        result = await self._drive_node(run, node, name, phase, verdict)
                    except Exception as exc:  # a bug: this node fails, the run ends cleanly
                        log.exception("run %s: driving %s failed", run.id, name)
                        result = {"node": name, "node_id": node.key if node else None, "outcome": "failed",
                                  "steps": [], "message": f"the gateway could not drive it ({exc})"}
                    if result["outcome"] == "failed" and run.policy == "stop" and not stopped_by:
                        stopped_by.append(name)
            progress.finished(result)

        for phase in phases:
            tiers = [list(reversed(t)) for t in reversed(run.tiers)] if phase.reverse else run.tiers
            for tier in tiers:
                # A failure stops the tiers after its own: the nodes of a tier have no order between
                # them, so which of them fails first must not decide which of the others are driven.
                stopped = bool(stopped_by)
                await asyncio.gather(*(drive(name, phase, stopped) for name in tier))
        results = progress.results()
        failed = sum(r["outcome"] == "failed" for r in results)
        if verdict.ended:
            status = verdict.status or "failed"  # the site's, if it ended the run
        elif not failed:
            status = "succeeded"
        elif stopped_by or failed == len(results):
            status = "failed"
        else:
            status = "partial"
        summary = ", ".join(f"{sum(r['outcome'] == o for r in results)} {o.replace('_', ' ')}"
                            for o in ("succeeded", "skipped", "failed", "not_run")
                            if any(r["outcome"] == o for r in results))
        summary = summary or "no nodes"
        if verdict.ended:
            summary = f"stopped: {verdict.ended}; {summary}"
        await progress.close()
        self.report(run, status, summary, results, started=started, finished=True)
        await progress.push(status=status, message=summary)
        log.info("run %s (%s of %s): %s", run.id, run.operation, run.robot.name, summary)

    async def _drive_node(self, run: Run, node: LiveNode | None, name: str, phase: Phase,
                          verdict: RunVerdict) -> dict:
        result = {"node": name, "node_id": node.key if node else None, "steps": [], "outcome": "succeeded",
                  "message": ""}
        if (phase.target == operations.EACH_NODES_OWN and run.targets.get(name) is None
                and not run.parameters.get(name)):
            return {**result, "outcome": "skipped", "message": "left alone (the mode does not say)"}
        if node is None or not node.alive:
            return {**result, "outcome": "failed", "message": f"{name} is not running"}
        began = time.perf_counter()
        try:
            # Bound everything, waiting for a busy node included: per step a call, re-reads, settling.
            async with asyncio.timeout(run.node_timeout * (4 + SETTLE_TIMEOUTS) * 4 + 5):
                async with node.lock:
                    state = await self._settled_state(node, run.node_timeout)
                    if phase.target == operations.EACH_NODES_OWN:
                        return await self._drive_to_own(run, node, name, phase, state, result, verdict, began)
                    target = phase.target
                    if state in phase.leave_alone:
                        return {**result, "outcome": "skipped", "state": sm.state_dict(state),
                                "message": f"left alone ({sm.state_label(state)})"}
                    steps = sm.path(state, target)
                    if steps is None:
                        return {**result, "outcome": "failed", "state": sm.state_dict(state),
                                "message": f"cannot go from {sm.state_label(state)} to {sm.state_label(target)}"
                                + (" (restart its process)" if state == sm.FINALIZED else "")}
                    if not steps:
                        return {**result, "outcome": "skipped", "state": sm.state_dict(state),
                                "message": f"already {sm.state_label(state)}"}
                    await self._steps(run, node, steps, state, result, verdict)
        except NodeUnreachable as exc:
            result.update(outcome="failed", message=str(exc))
        except TimeoutError:
            result.update(outcome="failed", message="gave up waiting for the node (busy or hung)")
        return self._ended(node, result, began)

    @staticmethod
    def _ended(node: LiveNode, result: dict, began: float) -> dict:
        result["state"] = sm.state_dict(node.state_id)
        result["duration_ms"] = round((time.perf_counter() - began) * 1000, 1)
        return result

    async def _steps(self, run: Run, node: LiveNode, labels: list[str], state: int, result: dict,
                     verdict: RunVerdict) -> bool:
        """Carry out these transitions in turn; False (and the result says why) at the first that fails."""
        for label in labels:
            if not await verdict.may_step():
                result.update(outcome="failed", message=f"stopped before {label}: {verdict.ended}")
                if not result["steps"]:
                    result.update(outcome="not_run", message=f"not run: {verdict.ended}")
                return False
            step = await self._step(run, node, label, state)
            state = step["to"]["id"]
            result["steps"].append(step)
            if step["outcome"] != "succeeded":
                result.update(outcome="failed", message=step["message"])
                return False
        return True

    async def _drive_to_own(self, run: Run, node: LiveNode, name: str, phase: Phase, state: int, result: dict,
                            verdict: RunVerdict, began: float) -> dict:
        """A mode's step for one node (its lock held): in the down phase, down to its target if that
        is below; in the up phase, up to it, its parameters set before it is activated (or once it
        is there, or at once for a node the mode leaves alone)."""
        target = run.targets.get(name)
        values = run.parameters.get(name) if phase.only == operations.UP else None
        moves = target is not None and mode_plan.goes(phase.only, state, target)
        if not moves and not values:
            message = f"already {sm.state_label(state)}" if target == state else ""  # (else: the other phase's)
            return self._ended(node, {**result, "outcome": "skipped", "message": message}, began)
        steps = sm.path(state, target) if moves else []
        if steps is None:
            return self._ended(node, {**result, "outcome": "failed", "state": sm.state_dict(state),
                                      "message": f"cannot go from {sm.state_label(state)} to "
                                                 f"{sm.state_label(target)}"
                                                 + (" (restart its process)" if state == sm.FINALIZED else "")}, began)
        before = steps[:steps.index("activate")] if values and "activate" in steps else steps
        if await self._steps(run, node, before, state, result, verdict) and values:
            if await self._set_parameters(run, node, values, result, verdict):
                await self._steps(run, node, steps[len(before):], node.state_id, result, verdict)
        return self._ended(node, result, began)

    async def _set_parameters(self, run: Run, node: LiveNode, values: dict, result: dict,
                              verdict: RunVerdict) -> bool:
        if not await verdict.may_step():
            result.update(outcome="failed" if result["steps"] else "not_run",
                          message=f"stopped before its parameters were set: {verdict.ended}")
            return False
        began = time.perf_counter()
        if self.params is None:
            answers: list[dict] = [{"name": n, "successful": False, "reason": "not set by this gateway"}
                                   for n in values]
        else:
            answers, _ = await self.params.set(node, values, run.node_timeout, run.source, run.user_id,
                                               run_id=run.id)
        refused = [a for a in answers if not a["successful"]]
        message = "; ".join(f"{a['name']}: {a['reason']}" for a in refused)
        result["steps"].append({"transition": mode_plan.SET_PARAMETERS, "outcome": "failed" if refused else "succeeded",
                                "message": message or ", ".join(f"{n}={v!r}" for n, v in values.items()),
                                "duration_ms": round((time.perf_counter() - began) * 1000, 1),
                                "to": sm.state_dict(node.state_id)})
        if refused:
            result.update(outcome="failed", message=f"parameters refused: {message}")
        return not refused

    async def _step(self, run: Run, node: LiveNode, label: str, state: int) -> dict:
        """One transition; ``state`` is the node's state as just read or reached (no re-read)."""
        try:
            driven = await self.driver.transition(
                node, label, run.node_timeout, source=run.source, user_id=run.user_id, run_id=run.id,
                known_state=state if sm.is_primary(state) else None,
            )
        except NodeUnreachable as exc:
            return {"transition": label, "outcome": "failed", "message": str(exc), "duration_ms": 0.0,
                    "fact_id": getattr(exc, "fact", {}).get("id"), "to": sm.state_dict(node.state_id)}
        outcome = driven.result
        status, message = outcome.outcome, outcome.message
        if status == "timed_out":
            # Nav2 calls this a failure without looking; the node may just have been slow.
            state = await self._settled_state(node, SETTLE_TIMEOUTS * run.node_timeout)
            goal = sm.SUCCESS_GOAL.get(outcome.transition.id) if outcome.transition else None
            if state == goal:
                status, message = "succeeded", f"slow: answered after the timeout, but reached {sm.state_label(state)}"
        return {"transition": label, "outcome": status, "message": message,
                "duration_ms": round(outcome.duration_ms, 1), "fact_id": driven.record["id"],
                "to": sm.state_dict(node.state_id)}

    async def _settled_state(self, node: LiveNode, timeout: float) -> int:
        """The node's real state, waiting (bounded) while it is inside a transition."""
        domain = self.domains[node.robot.domain_id]
        deadline = time.monotonic() + timeout
        while True:
            state = await read_state(domain, node.name, timeout)
            if sm.is_primary(state) or time.monotonic() >= deadline:
                self.registry.set_state(node, state)
                return state
            await asyncio.sleep(0.1)
