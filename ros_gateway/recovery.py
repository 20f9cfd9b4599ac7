"""Automatic recovery: a node whose process was restarted comes back unconfigured; where its robot
wants it, the gateway drives it back to the state an operator asked for (its desired state), as a
group run of its own (source "recovery"). With a crash-loop guard: a node recovered RECOVERY_LIMIT
times within RECOVERY_WINDOW_S is given up, unless the restarts were asked for (forgive).
"""
from __future__ import annotations

import asyncio
import logging
import time

from ros_gateway.groups import GroupRunner, Run
from ros_gateway.registry import LiveNode, RobotInfo
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm
from ros_gateway.shared.operations import Phase
from ros_gateway.tasks import spawn

log = logging.getLogger(__name__)

# Crash-loop guard: at most this many recoveries of one node within the window.
RECOVERY_LIMIT, RECOVERY_WINDOW_S = 3, 300.0
# After someone (re)starts a launch profile's process, its nodes' recoveries for this long are
# that restart's, not a crash loop's (the new process's nodes appear a second or more later).
FORGIVE_S = 30.0
# The nodes of a restarted process come back within moments of each other (their states read
# one by one): those of one robot are gathered until none came for GATHER_QUIET_S (at most
# GATHER_MAX_S) and recovered as one run.
GATHER_QUIET_S, GATHER_MAX_S = 0.1, 1.0


class Recovery:
    def __init__(self, runner: GroupRunner) -> None:
        self.runner, self.registry = runner, runner.registry
        self.recovering: set[str] = set()  # node keys with a recovery under way
        self.recent_recoveries: dict[str, list[float]] = {}
        self.forgiven: dict[tuple[str, str], float] = {}  # (robot, process) -> until (monotonic)
        self.recover_again: dict[str, str] = {}  # node key -> desired state, once its recovery under way ends
        self.gathering: dict[tuple[int, str], list[LiveNode]] = {}  # (robot id, desired state) -> nodes back

    def forgive(self, robot: str, process: str) -> None:
        """Someone restarted (or started) the launch profile's process: the recoveries of its
        nodes so far, and for FORGIVE_S from now, are not a crash loop's and do not count towards
        giving up on them. (A node not matched to its process yet counts as that process's.)"""
        now = time.monotonic()
        self.forgiven = {k: until for k, until in self.forgiven.items() if until > now}
        self.forgiven[(robot, process)] = now + FORGIVE_S
        for node in list(self.registry.nodes.values()):
            if self._forgiven(node, now):
                self.recent_recoveries.pop(node.key, None)

    def _forgiven(self, node: LiveNode, now: float) -> bool:
        return any(until > now and node.robot.name == robot and node.process in (process, "")
                   for (robot, process), until in self.forgiven.items())

    def on_change(self, change) -> None:
        """State-change listener: a node whose process was restarted comes back unconfigured;
        if its robot wants it, bring it back to the state an operator asked for. The nodes of one
        process come back within moments of each other: they are gathered into one run."""
        node = change.node
        if not change.respawned or not node.robot.auto_recover:
            return
        desired = self.registry.node_settings(node.robot.id, node.name).desired_state
        state_id = change.state_id
        wanted = desired in sm.DESIRED_STATES and sm.state_label(state_id) != desired
        if wanted and sm.is_primary(state_id) and state_id != sm.FINALIZED:
            batch = self.gathering.setdefault((node.robot.id, desired), [])
            if node not in batch:
                batch.append(node)
            if len(batch) == 1:
                spawn(self._gathered(node.robot.id, desired))

    async def _gathered(self, robot_id: int, desired: str) -> None:
        """Recover what came back for one robot and desired state once no more came for a moment."""
        began, count = time.monotonic(), 0
        while count != len(self.gathering[robot_id, desired]) and time.monotonic() - began < GATHER_MAX_S:
            count = len(self.gathering[robot_id, desired])
            await asyncio.sleep(GATHER_QUIET_S)
        await self.recover_nodes(self.gathering.pop((robot_id, desired)), desired)

    async def recover(self, node: LiveNode, desired: str) -> None:
        await self.recover_nodes([node], desired)

    async def recover_nodes(self, nodes: list[LiveNode], desired: str) -> None:
        """Drive nodes that came back (after their process was restarted) to their desired state,
        as one run in the robot's order. A node that comes back again while its recovery runs
        (restarted twice in a row) is recovered again once that one ends: the first was for a
        process that is gone."""
        now, robot, taken = time.monotonic(), nodes[0].robot, []
        for node in nodes:
            if node.key in self.recovering:
                self.recover_again[node.key] = desired
                continue
            recent = [t for t in self.recent_recoveries.get(node.key, []) if now - t < RECOVERY_WINDOW_S]
            if len(recent) >= RECOVERY_LIMIT:
                self._give_up(node, len(recent))
                continue
            if not self._forgiven(node, now):
                self.recent_recoveries[node.key] = [*recent, now]
            taken.append(node)
        if not taken:
            return
        run = Run(id=protocol.new_id(), robot=robot, operation="recover", tiers=self._in_order(robot, taken),
                  source="recovery")
        spec = {"operation": "recover", "only_nodes": [name for tier in run.tiers for name in tier],
                "source": "recovery", "policy": "continue", "node_timeout": run.node_timeout}
        keys = {node.key for node in taken}
        self.recovering |= keys
        try:
            log.info("recovering %d node(s) of %s to %s", len(taken), robot.name, desired)
            self.runner.report(run, "queued", f"back to {desired}", [], **spec)
            await self.runner.execute(run, (Phase(sm.DESIRED_STATES[desired]),))
        finally:
            self.recovering -= keys
        for node in taken:
            again = self.recover_again.pop(node.key, None)
            if again is not None and node.alive:
                spawn(self.recover(node, again))

    def _give_up(self, node: LiveNode, count: int) -> None:
        run = Run(id=protocol.new_id(), robot=node.robot, operation="recover", tiers=[[node.name]], source="recovery")
        message = (f"gave up: {count} recoveries in the last {RECOVERY_WINDOW_S / 60:.0f} min "
                   "(the node keeps dying); bring it up by hand once the cause is fixed")
        log.error("not recovering %s:%s: %s", node.robot.name, node.name, message)
        self.runner.report(run, "failed", message, [], finished=True, operation="recover", only_nodes=[node.name],
                     source="recovery", policy="stop", node_timeout=run.node_timeout)

    def _in_order(self, robot: RobotInfo, nodes: list[LiveNode]) -> list[list[str]]:
        """The nodes as tiers of the robot's bring-up order (as the site's runs have them): one tier
        per position, then those without one."""
        by_position: dict[int | None, list[str]] = {}
        for node in sorted(nodes, key=lambda n: n.name):
            by_position.setdefault(self.registry.node_settings(robot.id, node.name).order, []).append(node.name)
        return [by_position[p] for p in sorted(by_position, key=lambda p: (p is None, p or 0))]

