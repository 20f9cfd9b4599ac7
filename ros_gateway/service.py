"""The gateway worker: watches robots' ROS domains and keeps the site's facts current.

One asyncio loop owns all bookkeeping; each watched domain has its own rclpy Context and
executor thread (domain.py). Loops here: robots (which domains to watch), discovery
(which lifecycle nodes exist), state resync, heartbeat, logs (logs.py) and commands
(commands.py). Any single failure is logged and the loop goes on.
"""
from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone

from django.conf import settings

from ros_gateway import store
from ros_gateway.commands import CommandHandler
from ros_gateway.domain import RosDomain
from ros_gateway.driver import NodeDriver
from ros_gateway.groups import GroupRunner
from ros_gateway.lifecycle import NodeUnreachable, read_state
from ros_gateway.logs import LogPipeline
from ros_gateway.param_keeper import ParameterKeeper
from ros_gateway.relay import Relay
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm
from ros_gateway.store import db
from ros_gateway.streams import Completed, TransitionTracker

log = logging.getLogger(__name__)

# After a domain starts, discovery needs a moment before "not in the graph" means "gone".
DISCOVERY_SETTLE_S = 3.0


@dataclass
class LiveNode:
    """What the gateway knows of one lifecycle node it has seen."""

    robot: store.RobotInfo
    name: str
    row: store.NodeRow
    alive: bool = False  # believed running (as the site shows it)
    seen: bool = False  # found in the ROS graph by this gateway run, and subscribed to
    # Set when this run saw the node go and come back, or its process replaced: worth recovering.
    respawned: bool = False
    incarnation: frozenset = frozenset()
    state_id: int = sm.UNKNOWN
    state_read: bool = False  # the state has been read from the node since it appeared
    tracker: TransitionTracker = field(default_factory=TransitionTracker)
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)  # one transition at a time
    # State updates go out (push, then disk) strictly in the order they were made.
    update_lock: asyncio.Lock = field(default_factory=asyncio.Lock)
    last_seen: datetime | None = None

    @property
    def key(self) -> str:
        return self.row.key

    def payload(self) -> dict:
        return protocol.node_payload(
            key=self.key,
            robot=self.robot.name,
            name=self.name,
            state_id=self.state_id,
            alive=self.alive,
            last_seen=self.last_seen.isoformat() if self.last_seen else None,
        )

    def groups(self) -> list[str]:
        return [protocol.node_group(self.key), protocol.robot_group(self.robot.id), protocol.FLEET_GROUP]


class Gateway:
    def __init__(self, name: str = "gateway") -> None:
        self.name = name
        self.config = settings.LIFECYCLE
        self.loop: asyncio.AbstractEventLoop | None = None
        self.relay = Relay()
        self.robots: dict[int, store.RobotInfo] = {}
        self.domains: dict[int, RosDomain] = {}
        # (domain id, fully qualified node name) -> node
        self.nodes: dict[tuple[int, str], LiveNode] = {}
        self.started = datetime.now(timezone.utc)
        self._stopping = asyncio.Event()
        self._background: set[asyncio.Task] = set()
        self.logs = LogPipeline(self)
        self.commands = CommandHandler(self)
        self.params = ParameterKeeper(self)
        self.driver = NodeDriver(self)
        self.groups = GroupRunner(self)
        self._passes = 0

    # -- running ----------------------------------------------------------------------
    async def run(self) -> None:
        self.loop = asyncio.get_running_loop()
        loops = [
            self._every(self.config["ROBOT_REFRESH_INTERVAL"], self.refresh_robots, "robot refresh"),
            self._every(self.config["DISCOVERY_INTERVAL"], self.discover, "discovery"),
            self._every(self.config["HEARTBEAT_INTERVAL"], self.heartbeat, "heartbeat"),
            self._every(30.0, self.resync_states, "state resync"),
            self._every(30.0, self.touch_alive, "last-seen update"),
            self.logs.run(self._stopping),
            self.commands.run(self._stopping),
        ]
        await self.refresh_robots()
        await self.heartbeat()
        log.info("ROS gateway %r running", self.name)
        tasks = [asyncio.create_task(c) for c in loops]
        await self._stopping.wait()
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        await self.logs.flush()
        for domain in list(self.domains.values()):
            await asyncio.to_thread(domain.stop)
        await db(store.gateway_stopped)(self.name)
        await self.relay.close()

    def stop(self) -> None:
        self._stopping.set()

    async def _every(self, interval: float, job, what: str) -> None:
        while not self._stopping.is_set():
            try:
                await job()
            except Exception:
                log.exception("%s failed; trying again in %.1f s", what, interval)
            try:
                await asyncio.wait_for(self._stopping.wait(), interval)
            except asyncio.TimeoutError:
                pass

    def spawn(self, coroutine) -> None:
        """Run a coroutine in the background, keeping a reference and logging its failure."""
        task = asyncio.ensure_future(coroutine)
        self._background.add(task)
        task.add_done_callback(self._background_done)

    def _background_done(self, task: asyncio.Task) -> None:
        self._background.discard(task)
        if not task.cancelled() and task.exception() is not None:
            log.error("background task failed", exc_info=task.exception())

    # -- robots and domains ---------------------------------------------------------------
    async def refresh_robots(self) -> None:
        robots = {r.id: r for r in await db(store.load_robots)()}
        for robot_id, old in list(self.robots.items()):
            if robots.get(robot_id) != old:  # removed, disabled or changed: forget its nodes
                await self._drop_robot_nodes(old)
        for robot in robots.values():
            if self.robots.get(robot.id) != robot:
                await self._adopt_known_nodes(robot)
        self.robots = robots
        wanted = {r.domain_id for r in robots.values()}
        for domain_id in wanted - set(self.domains):
            domain = RosDomain(
                domain_id, self.loop, self.on_transition_event, self.logs.on_log, self.params.on_event
            )
            await asyncio.to_thread(domain.start)
            self.domains[domain_id] = domain
        for domain_id in set(self.domains) - wanted:
            domain = self.domains.pop(domain_id)
            await asyncio.to_thread(domain.stop)

    async def _adopt_known_nodes(self, robot: store.RobotInfo) -> None:
        """Take over what the database believes of a robot's nodes: those said to be running
        stay so until discovery has had its chance, then they are seen again or marked lost."""
        for name, row in (await db(store.load_nodes)(robot.id)).items():
            if row.alive and (robot.domain_id, name) not in self.nodes:
                self.nodes[(robot.domain_id, name)] = LiveNode(
                    robot=robot, name=name, row=row, alive=True, state_id=row.state_id
                )

    async def _drop_robot_nodes(self, robot: store.RobotInfo) -> None:
        gone = [(k, n) for k, n in self.nodes.items() if n.robot.id == robot.id]
        for key, node in gone:
            del self.nodes[key]
            domain = self.domains.get(key[0])
            if domain is not None:
                domain.forget_node(node.name)
        ids = [n.row.id for _, n in gone if n.alive]
        if ids:
            await db(store.nodes_lost)(ids)

    def robot_for(self, domain_id: int, node_name: str) -> store.RobotInfo | None:
        """The robot owning a node: same domain, the longest matching namespace."""
        owners = [r for r in self.robots.values() if r.domain_id == domain_id and r.owns(node_name)]
        return max(owners, key=lambda r: len(r.namespace), default=None)

    def find_node(self, robot_name: str, node_name: str) -> LiveNode | None:
        for node in self.nodes.values():
            if node.robot.name == robot_name and node.name == node_name:
                return node
        return None

    # -- discovery ------------------------------------------------------------------------
    async def discover(self) -> None:
        self._passes += 1
        check_incarnations = self._passes % 4 == 0
        for domain_id, domain in list(self.domains.items()):
            present = domain.lifecycle_node_names()
            for name in present:
                node = self.nodes.get((domain_id, name))
                if node is None or not node.seen:
                    robot = self.robot_for(domain_id, name)
                    if robot is not None:
                        await self._appeared(domain, robot, name)
                elif not node.state_read:
                    self.spawn(self._read_state(domain, node))
                elif check_incarnations:
                    self._check_incarnation(domain, node)
            if time.monotonic() - domain.started_at < DISCOVERY_SETTLE_S:
                continue
            for (node_domain, name), node in list(self.nodes.items()):
                if node_domain == domain_id and node.alive and name not in present:
                    await self._vanished(domain, node)

    async def _appeared(self, domain: RosDomain, robot: store.RobotInfo, name: str) -> None:
        row = await db(store.node_seen)(robot.id, name)
        node = self.nodes.get((domain.domain_id, name))
        if node is None:
            node = LiveNode(robot=robot, name=name, row=row, state_id=row.state_id)
            self.nodes[(domain.domain_id, name)] = node
        node.alive, node.seen, node.state_read = True, True, False
        node.last_seen = datetime.now(timezone.utc)
        node.tracker = TransitionTracker()
        node.respawned = node.incarnation != frozenset()  # seen before in this run: it came back
        node.incarnation = domain.incarnation(name)
        self.params.forget(node.key)  # possibly a new process: its parameters are read afresh
        domain.watch_node(name)
        log.info("node %s appeared on %s", name, robot.name)
        await self.relay.publish(node.groups(), {"type": "node.state", "node": node.payload()})
        self.spawn(self._read_state(domain, node))

    async def _vanished(self, domain: RosDomain, node: LiveNode) -> None:
        node.alive, node.seen, node.last_seen = False, False, datetime.now(timezone.utc)
        domain.forget_node(node.name)
        log.info("node %s on %s is gone", node.name, node.robot.name)
        await db(store.nodes_lost)([node.row.id])
        await self.relay.publish(node.groups(), {"type": "node.state", "node": node.payload()})

    def _check_incarnation(self, domain: RosDomain, node: LiveNode) -> None:
        current = domain.incarnation(node.name)
        if len(current) > 1 and current != node.incarnation:
            # Service requests then reach every one of them and the first answer wins.
            log.warning("%d processes publish the transition events of %s on %s: a second node under the same "
                        "name, or a killed process whose DDS lease has not run out yet; its state may be misread",
                        len(current), node.name, node.robot.name)
        if current - node.incarnation and node.incarnation:
            log.info("%s on %s was restarted (new process under the same name)", node.name, node.robot.name)
            node.respawned, node.state_read = True, False
            node.tracker = TransitionTracker()
            self.params.forget(node.key)
        node.incarnation = current

    async def _read_state(self, domain: RosDomain, node: LiveNode) -> None:
        if node.lock.locked():
            return  # a command is running; it reads the state itself
        try:
            state_id = await read_state(domain, node.name, self.config["SERVICE_TIMEOUT"])
        except NodeUnreachable as exc:
            log.info("could not read the state of %s on %s: %s", node.name, node.robot.name, exc)
            return
        node.state_read = True
        await self.set_state(node, state_id)
        if node.respawned:
            node.respawned = False
            await self._maybe_recover(node, state_id)

    async def _maybe_recover(self, node: LiveNode, state_id: int) -> None:
        """A node whose process was restarted comes back unconfigured: if its robot wants it,
        bring it back to the state an operator asked for."""
        robot = self.robots.get(node.robot.id)
        if robot is None or not robot.auto_recover:
            return
        desired = await db(store.desired_state)(node.row.id)
        if desired and sm.is_primary(state_id) and state_id != sm.FINALIZED and sm.state_label(state_id) != desired:
            self.spawn(self.groups.recover(node, desired))

    async def _check_settled(self, node: LiveNode, state_id: int) -> None:
        await asyncio.sleep(2 * self.config["SERVICE_TIMEOUT"])
        domain = self.domains.get(node.robot.domain_id)
        if node.alive and node.state_id == state_id and domain is not None:
            await self._read_state(domain, node)

    async def resync_states(self) -> None:
        """Fallback for lost transition events: re-read every live node's state."""
        for (domain_id, _name), node in list(self.nodes.items()):
            domain = self.domains.get(domain_id)
            if domain is not None and node.alive:
                await self._read_state(domain, node)

    # -- state ----------------------------------------------------------------------------
    async def set_state(self, node: LiveNode, state_id: int) -> None:
        async with node.update_lock:
            if state_id == node.state_id and node.row.state_id == state_id:
                return
            if not sm.is_primary(state_id):
                # Safety net: a node should not sit in a transition state for long; if it does
                # (a lost event, a hung callback), find out what it really is.
                self.spawn(self._check_settled(node, state_id))
            node.state_id = state_id
            node.last_seen = datetime.now(timezone.utc)
            node.row.state_id = state_id
            # The push and the disk write go together; the page waits for neither.
            await asyncio.gather(
                self.relay.publish(node.groups(), {"type": "node.state", "node": node.payload()}),
                db(store.save_state)(node.row.id, state_id),
            )

    def on_transition_event(self, domain_id: int, name: str, msg) -> None:
        """A node's ~/transition_event (called on the loop, handed over from the executor)."""
        node = self.nodes.get((domain_id, name))
        if node is None:
            return
        try:
            start, goal = int(msg.start_state.id), int(msg.goal_state.id)
            completed, news = node.tracker.observe(start, goal, int(msg.transition.id))
        except Exception:
            log.exception("ignored a malformed transition event from %s", name)
            return
        self.spawn(self._after_event(node, goal if news else None, completed))

    async def _after_event(self, node: LiveNode, state_id: int | None, completed: Completed | None) -> None:
        if state_id is not None:
            await self.set_state(node, state_id)
        if completed is None:
            return
        log.info("external transition on %s:%s: %s", node.robot.name, node.name, completed.outcome)
        record = await db(store.record_transition)(
            node_id=node.row.id,
            node_key=node.key,
            robot=node.robot,
            node_name=node.name,
            transition=completed.transition,
            start_state=completed.start_state,
            result_state=completed.result_state,
            outcome=completed.outcome,
            source="external",
            requested_at=completed.started_at,
            completed_at=completed.finished_at,
        )
        await self.publish_record(node, record)

    async def publish_record(self, node: LiveNode, record: dict) -> None:
        await self.relay.publish(node.groups(), {"type": "audit.record", "record": record})

    # -- housekeeping ---------------------------------------------------------------------
    async def heartbeat(self) -> None:
        await db(store.heartbeat)(self.name, self.started, list(self.domains))

    async def touch_alive(self) -> None:
        ids = [n.row.id for n in self.nodes.values() if n.alive]
        if ids:
            await db(store.nodes_still_alive)(ids)
