"""Which robots to watch (from the site's configuration), which lifecycle nodes run in their
domains, and what state each is in: the gateway's view of the ROS graph, kept current.

Domains are started and stopped as robots come and go; each discovery pass finds nodes that
appeared (subscribed to, state read) and vanished; transition events and a periodic re-read
keep the states right. Every change goes through the registry's state-change stream.
"""
from __future__ import annotations

import asyncio
import logging
import time
from typing import Callable

from ros_gateway.domain import RosDomain
from ros_gateway.lifecycle import NodeUnreachable, read_state
from ros_gateway.parts import Core
from ros_gateway.processes import ProcessRecords
from ros_gateway.registry import LiveNode, NodeSettings, RobotInfo, participants
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm
from ros_gateway.tasks import spawn
from ros_gateway.topic_messages import Completed, TransitionTracker

log = logging.getLogger(__name__)

# How often every robot's full list of running nodes is reported (the site marks the rest lost).
SNAPSHOT_EVERY_S = 30.0
LEFT_GRAPH = "ended: its node left the ROS graph (or was shut down)"
# Time per discovery pass spent looking for restarted processes (one graph query per node):
# a few nodes are all checked every pass; a thousand are checked in turn, a slice per pass, so
# a pass never stalls the event loop that also reads the nodes' logs.
INCARNATION_BUDGET_S = 0.004
# After this gateway (re)started a process, its nodes appear within moments: the passes come this
# often for a while, so that they are found (and recovered) without waiting for the next pass.
HURRIED_INTERVAL_S, HURRY_FOR_S = 0.1, 5.0

DomainFactory = Callable[[int], RosDomain]
# (domain, node name, processes known ended) -> whether the node's process is known not to answer
HoldsBack = Callable[[RosDomain, str, frozenset], bool]


def robots_from_config(config: dict) -> tuple[dict[int, RobotInfo], dict[int, dict[str, NodeSettings]]]:
    """The site's configuration as robots and per-node settings; malformed entries are skipped."""
    robots: dict[int, RobotInfo] = {}
    settings: dict[int, dict[str, NodeSettings]] = {}
    for entry in config.get("robots", []):
        try:
            robot = RobotInfo(int(entry["id"]), str(entry["name"]), int(entry["domain_id"]),
                              str(entry.get("namespace") or ""), bool(entry.get("auto_recover")))
        except (KeyError, TypeError, ValueError):
            log.warning("ignored a robot the site described incompletely: %r", entry)
            continue
        robots[robot.id] = robot
        nodes = entry.get("nodes") if isinstance(entry.get("nodes"), dict) else {}
        settings[robot.id] = {
            str(name): NodeSettings(order=s.get("order") if isinstance(s.get("order"), int) else None,
                                    desired_state=str(s.get("desired_state") or ""), keep=str(s.get("keep") or "off"),
                                    resumed=str(s.get("resumed") or ""))
            for name, s in nodes.items() if isinstance(s, dict)
        }
    return robots, settings


class Discovery:
    def __init__(self, core: Core, new_domain: DomainFactory, forget_parameters: Callable[[str], None],
                 holds_back: HoldsBack = lambda domain, name, departed: False,
                 unresponsive: Callable[[LiveNode], None] = lambda node: None) -> None:
        self.registry, self.domains, self.new_domain, self.outbox = core.registry, core.domains, new_domain, core.outbox
        self.processes = core.processes
        self.records = ProcessRecords(core.outbox)
        self.unresponsive = unresponsive
        self.service_timeout = core.service_timeout
        self.forget_parameters = forget_parameters
        self.holds_back = holds_back
        self.on_external: Callable[[LiveNode], None] = lambda node: None  # a transition by another tool ended
        self.config_version: str | None = None
        self._incarnation_cursor: dict[int, str] = {}  # domain id -> name of the last node checked
        self._snapshot_at: dict[int, float] = {}  # robot id -> when its node list was last reported
        self._hurried_until = 0.0  # (monotonic)
        self._first_reads: set[str] = set()  # keys of nodes whose state is being read since they appeared

    def hurry(self) -> None:
        """A process was (re)started on this host: look for its nodes often for HURRY_FOR_S."""
        self._hurried_until = time.monotonic() + HURRY_FOR_S

    def pause(self, interval: float) -> float:
        """The time until the next pass: ``interval``, shorter while hurried."""
        return min(interval, HURRIED_INTERVAL_S) if time.monotonic() < self._hurried_until else interval

    # -- robots and domains -------------------------------------------------------------
    async def apply_config(self, config: dict) -> None:
        """Watch the robots the site lists for this gateway (and only those)."""
        version = str(config.get("version", ""))
        if version and version == self.config_version:
            return
        robots, settings = robots_from_config(config)
        for robot_id, old in list(self.registry.robots.items()):
            new = robots.get(robot_id)
            if new is not None and (new.domain_id, new.namespace) == (old.domain_id, old.namespace):
                for node in self.registry.of_robot(robot_id):  # renamed, recovery switched: same nodes
                    node.robot = new
                continue
            if new != old:  # removed, disabled, or its nodes are elsewhere now: forget its nodes
                for node in self.registry.of_robot(robot_id):
                    if node.alive:  # no longer watched: the site shows it lost until seen again
                        self.registry.vanished(node)
                for domain_id, node in self.registry.drop_robot(robot_id):
                    domain = self.domains.get(domain_id)
                    if domain is not None:
                        domain.forget_node(node.name)
                self._snapshot_at.pop(robot_id, None)
        self.registry.robots, self.registry.settings = robots, settings
        wanted = self.registry.domains()
        for domain_id in wanted - set(self.domains):
            domain = self.new_domain(domain_id)
            await asyncio.to_thread(domain.start)
            self.domains[domain_id] = domain
        for domain_id in set(self.domains) - wanted:
            domain = self.domains.pop(domain_id)
            await asyncio.to_thread(domain.stop)
        self.config_version = version
        log.info("watching %d robot(s) in ROS domain(s) %s", len(robots), sorted(wanted) or "none")

    # -- discovery ------------------------------------------------------------------------
    async def discover(self) -> None:
        deadline = time.monotonic() + INCARNATION_BUDGET_S
        for domain_id, domain in list(self.domains.items()):
            if self.processes.host is None:
                self.processes.learn_host(domain.own_gid())
            present = domain.lifecycle_node_names(name for d, name in self.registry.nodes if d == domain_id)
            settled: list[LiveNode] = []
            for name in present:
                node = self.registry.nodes.get((domain_id, name))
                if node is None or not node.seen:
                    robot = self.registry.robot_for(domain_id, name)
                    if robot is not None and not self._held_back(domain, node, name):
                        self._appeared(domain, robot, name)
                elif not node.state_read:
                    self._read_first(node)
                elif not node.in_transition:  # a transition of ours watches it
                    settled.append(node)
            self._check_incarnations(domain, settled, deadline)
            domain.drop_kept()
            if domain.settling():
                continue
            # A transition of ours watches the process itself (and records its loss).
            watched = [node for (node_domain, _), node in list(self.registry.nodes.items())
                       if node_domain == domain_id and node.alive and not node.in_transition]
            ended = self.processes.ended_among(domain_id, (prefix for node in watched for prefix in node.live))
            for node in watched:
                if node.name not in present:
                    self._lost(domain, node, LEFT_GRAPH)
                elif self.processes.all_ended(domain_id, node.live, ended):
                    self._lost(domain, node, "exited (seen on this host)", ended=True)
            self._report_robots(domain)

    def _held_back(self, domain: RosDomain, node: LiveNode | None, name: str) -> bool:
        """Whether the node is in the graph only by processes known to have ended or left (a
        killed process stays there until its DDS lease runs out, 20 s by default) or that do
        not answer (liveness.py)."""
        current = participants(domain.incarnation(name))
        gone = (node.departed if node else frozenset()) | self.processes.ended_among(domain.domain_id, current)
        return bool(current) and current <= gone or self.holds_back(domain, name, frozenset(gone))

    def _lost(self, domain: RosDomain, node: LiveNode, how: str, ended: bool = False) -> None:
        domain.forget_node(node.name, keep=True)
        self.registry.vanished(node, reason=protocol.PROCESS_LOST, ended=ended)
        self.records.lost(node, how)

    def _report_robots(self, domain: RosDomain) -> None:
        """Each settled robot's running nodes, now and then: what the site believes alive
        but this gateway does not see (after a restart of either) is marked lost."""
        now = time.monotonic()
        for robot in self.registry.robots.values():
            if robot.domain_id != domain.domain_id or now - self._snapshot_at.get(robot.id, 0.0) < SNAPSHOT_EVERY_S:
                continue
            self._snapshot_at[robot.id] = now
            names = sorted(n.name for n in self.registry.of_robot(robot.id) if n.alive)
            self.outbox.emit(protocol.ROBOT_NODES, robot=robot.name, nodes=names)

    def _appeared(self, domain: RosDomain, robot: RobotInfo, name: str) -> None:
        node = self.registry.appeared(domain.domain_id, robot, name, domain.incarnation(name))
        self.forget_parameters(node.key)  # possibly a new process: its parameters are read afresh
        domain.watch_node(name)
        log.info("node %s appeared on %s", name, robot.name)
        self._read_first(node)

    def _check_incarnations(self, domain: RosDomain, nodes: list[LiveNode], deadline: float) -> None:
        """Check nodes in name order from where the last pass stopped, until ``deadline`` (at
        least one per pass, so every node's turn comes)."""
        if not nodes:
            return
        nodes.sort(key=lambda n: n.name)
        last = self._incarnation_cursor.get(domain.domain_id, "")
        start = next((i for i, n in enumerate(nodes) if n.name > last), 0)
        for count, node in enumerate(nodes[start:] + nodes[:start]):
            if count and time.monotonic() >= deadline:
                break
            if node.alive:  # an earlier check of this pass may have found it lost
                self._check_incarnation(domain, node)
            self._incarnation_cursor[domain.domain_id] = node.name

    def _check_incarnation(self, domain: RosDomain, node: LiveNode) -> None:
        """A new process under the node's name (restarted), or the one we knew gone from the
        graph while a dead one lingers under the name (it left)."""
        current = domain.incarnation(node.name)
        now = participants(current)
        node.departed &= now  # gone from the graph: no need to remember them
        if len(now - node.departed) > 1 and current != node.incarnation:
            # Service requests then reach every one of them and the first answer wins.
            log.warning("%d processes publish the transition events of %s on %s: a second node under the same "
                        "name, or a killed process whose DDS lease has not run out yet; its state may be misread",
                        len(now - node.departed), node.name, node.robot.name)
        # Kept while none is listed (its endpoints gone before its name left the graph): that it was
        # seen with some is what tells its next appearance a new instance (registry.appeared).
        node.incarnation = current or node.incarnation
        if node.live & now:
            node.live &= now  # a process that stopped publishing is not the one it runs in
        new = now - node.live - node.departed
        if new and node.live:
            log.info("%s on %s was restarted (new process under the same name)", node.name, node.robot.name)
            node.departed, node.live = node.departed | node.live, new
            node.respawned, node.state_read = True, False
            node.tracker = TransitionTracker()
            self.forget_parameters(node.key)
        elif new:
            node.live = new  # its endpoints, seen after it appeared
        elif node.live and not now & node.live:
            self._lost(domain, node, LEFT_GRAPH)

    def _read_first(self, node: LiveNode) -> None:
        """Read the state of a node that appeared (or came back), once at a time: a pass that
        finds it still unread while a read is under way adds none (that read is sent again
        while unanswered, domain.RESEND_AFTER_S)."""
        key = node.key  # (as it is now: a robot renamed meanwhile changes it)
        if key not in self._first_reads:
            self._first_reads.add(key)
            spawn(self.read_state(node)).add_done_callback(lambda _: self._first_reads.discard(key))

    async def read_state(self, node: LiveNode) -> bool | None:
        """Read the node's state; False if it did not answer, None if not asked (a command
        on it is running and reads the state itself)."""
        domain = self.domains.get(node.robot.domain_id)
        if domain is None or node.lock.locked():
            return None
        try:
            state_id = await read_state(domain, node.name, self.service_timeout)
        except NodeUnreachable as exc:
            log.info("could not read the state of %s on %s: %s", node.name, node.robot.name, exc)
            return False
        self.registry.set_state(node, state_id, read=True)
        return True

    async def resync_states(self) -> None:
        """Fallback for lost transition events: re-read every live node's state."""
        for node in list(self.registry.nodes.values()):
            if node.alive:
                await self.read_state(node)

    def on_change(self, change) -> None:
        """State-change listener: a node should not sit in a transition state for long; if it
        does (a lost event, a hung callback), find out what it really is."""
        if change.kind == "state" and not sm.is_primary(change.state_id):
            spawn(self._check_settled(change.node, change.state_id))

    async def _check_settled(self, node: LiveNode, state_id: int) -> None:
        await asyncio.sleep(2 * self.service_timeout)
        if node.alive and node.state_id == state_id and await self.read_state(node) is False:
            # Stuck in a transition and silent: its process may be gone (killed in the middle
            # of a transition), which only the DDS lease would tell, 20 s or more from now.
            self.unresponsive(node)

    # -- transition events (handed over from the executor threads) -----------------------
    def on_transition_event(self, domain_id: int, name: str, msg) -> None:
        node = self.registry.nodes.get((domain_id, name))
        if node is None:
            return
        try:
            start, goal = int(msg.start_state.id), int(msg.goal_state.id)
            completed, news = node.tracker.observe(start, goal, int(msg.transition.id))
        except Exception:
            log.exception("ignored a malformed transition event from %s", name)
            return
        if news:
            self.registry.set_state(node, goal)
        if completed is not None:
            self._report_external(node, completed)

    def _report_external(self, node: LiveNode, completed: Completed) -> None:
        log.info("external transition on %s:%s: %s", node.robot.name, node.name, completed.outcome)
        transition = completed.transition
        self.outbox.emit(
            protocol.TRANSITION, robot=node.robot.name, node=node.name,
            transition_id=transition.id if transition else None,
            transition_label=transition.label if transition else "",
            start_state=completed.start_state, result_state=completed.result_state, outcome=completed.outcome,
            source="external", user_id=None, requested_at=completed.started_at.isoformat(),
            completed_at=completed.finished_at.isoformat(), error="", run_id="",
        )
        self.on_external(node)
