"""Desired states kept against other tools (a node's policy "enforce"): a node moved away from its
desired state by another tool (a transition that was not ours) is driven back after GRACE_S, as a
run of source "recovery".

Without fights: another manager (Nav2's lifecycle_manager, a team's bring-up script) would move
the node away again at once, and the two would take turns for ever. A node moved away a
FIGHT_LIMIT-th time within FIGHT_WINDOW_S is left alone: the site is told (an
ENFORCEMENT_STOPPED fact: the node's pages say so, an alert fires), and the site's config then
says "paused" for it. Enforcement resumes only when an operator says so: the config goes from
"paused" back to "enforce"."""
from __future__ import annotations

import asyncio
import logging
import time
from datetime import datetime, timezone
from typing import Awaitable, Callable

from ros_gateway.groups import GroupRunner, Run
from ros_gateway.registry import LiveNode, NodeRegistry
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm
from ros_gateway.shared.operations import Phase
from ros_gateway.tasks import spawn

log = logging.getLogger(__name__)

GRACE_S = 2.0  # a tool that moves a node through several transitions is given time to finish
FIGHT_LIMIT, FIGHT_WINDOW_S = 3, 600.0  # changes undone within the window before the node is left alone
ENFORCE = "enforce"


class DesiredKeeper:
    def __init__(self, runner: GroupRunner, registry: NodeRegistry,
                 read_state: Callable[[LiveNode], Awaitable[bool | None]] | None = None) -> None:
        self.runner, self.registry, self.outbox = runner, registry, runner.outbox
        # Discovery's read of a node's state into the registry (True: read).
        self.read_state = read_state
        self.undone: dict[str, list[float]] = {}  # node key -> when its changes were undone (monotonic)
        # Left alone after a fight -> the site's "resumed" for it then: a later one resumes keeping it.
        self.stopped: dict[str, str] = {}
        self.waiting: set[str] = set()  # a change of theirs within its grace, or being undone
        self.missed: set[str] = set()  # ... and another change came meanwhile

    def _keep(self, node: LiveNode) -> tuple[str, str]:
        settings = self.registry.node_settings(node.robot.id, node.name)
        return settings.keep, settings.desired_state

    def _resumed(self, node: LiveNode) -> str:
        return self.registry.node_settings(node.robot.id, node.name).resumed

    def on_external(self, node: LiveNode) -> None:
        """Discovery: another tool's transition on the node ended."""
        keep, desired = self._keep(node)
        if keep != ENFORCE or desired not in sm.DESIRED_STATES or node.key in self.stopped:
            return
        if node.key in self.waiting:
            self.missed.add(node.key)  # while its change was being undone: looked at again after
            return
        self.waiting.add(node.key)
        spawn(self._undo(node, datetime.now(timezone.utc)))

    def on_settings(self) -> None:
        """After each config from the site: resume a stopped node an operator resumed since (or
        no longer kept at all)."""
        for key, resumed_before in list(self.stopped.items()):
            node = next((n for n in self.registry.nodes.values() if n.key == key), None)
            keep = self._keep(node)[0] if node is not None else "off"
            if keep not in (ENFORCE, protocol.KEEP_PAUSED) or self._resumed(node) != resumed_before:
                del self.stopped[key]
                self.undone.pop(key, None)
                if keep == ENFORCE and node is not None and node.key not in self.waiting:
                    log.info("keeping %s in its desired state again (resumed by an operator)", key)
                    self.waiting.add(key)  # where another manager left it: back now (after the grace)
                    spawn(self._undo(node, datetime.now(timezone.utc)))

    async def _undo(self, node: LiveNode, changed_at: datetime) -> None:
        try:
            await asyncio.sleep(GRACE_S)
            keep, desired = self._keep(node)
            target = sm.DESIRED_STATES.get(desired)
            if keep != ENFORCE or target is None or not node.alive or node.in_transition:
                return
            if node.state_id == target and not await self._elsewhere_after_all(node, target):
                return
            if not sm.is_primary(node.state_id) or node.state_id == sm.FINALIZED:
                return
            now = time.monotonic()
            recent = [t for t in self.undone.get(node.key, []) if now - t < FIGHT_WINDOW_S]
            if len(recent) >= FIGHT_LIMIT:
                self._stop(node, len(recent) + 1, changed_at)
                return
            self.undone[node.key] = [*recent, now]
            log.info("%s on %s was moved to %s by another tool: back to %s", node.name, node.robot.name,
                     sm.state_label(node.state_id), desired)
            run = Run(id=protocol.new_id(), robot=node.robot, operation="recover", tiers=[[node.name]],
                      source="recovery")
            self.runner.report(run, "queued", f"back to {desired}: undoing a change by another tool", [],
                               operation="recover", only_nodes=[node.name], source="recovery", policy="stop",
                               node_timeout=run.node_timeout)
            await self.runner.execute(run, (Phase(target),))
        finally:
            self.waiting.discard(node.key)
            if node.key in self.missed:  # another tool moved it while this one was undone
                self.missed.discard(node.key)
                self.on_external(node)

    async def _elsewhere_after_all(self, node: LiveNode, target: int) -> bool:
        """Whether the node, in ``target`` as far as the registry knows, is elsewhere: the reply to
        our own last undo, handled after the other tool's next transition events, puts back the
        state that undo left (seen once under load: the node stayed as the other tool left it,
        neither undone nor given up). Read from the node."""
        if self.read_state is None or not await self.read_state(node):
            return False
        return node.state_id != target

    def _stop(self, node: LiveNode, changes: int, changed_at: datetime) -> None:
        self.stopped[node.key] = self._resumed(node)
        self.undone.pop(node.key, None)
        message = (f"another manager keeps changing {node.name} (moved away from its desired state {changes} times "
                   f"in {FIGHT_WINDOW_S / 60:.0f} min; last change by an external tool at "
                   f"{changed_at.strftime('%H:%M:%S')} UTC): the gateway stopped keeping it "
                   f"{self._keep(node)[1]} and leaves it alone until an operator resumes it")
        log.warning("%s on %s: %s", node.name, node.robot.name, message)
        self.outbox.emit(protocol.ENFORCEMENT_STOPPED, robot=node.robot.name, node=node.name, message=message,
                         changes=changes, window_s=FIGHT_WINDOW_S, last_change=changed_at.isoformat())
