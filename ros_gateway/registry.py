"""What the gateway knows of its robots and their live nodes, and the one place a node's
state changes: ``NodeRegistry.set_state`` and friends publish each change to ``StateChanges``,
whose listeners report it to the site, push it to pages and recover respawned nodes.
No rclpy and no Redis here."""
from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Callable

from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm
from ros_gateway.topic_messages import TransitionTracker

log = logging.getLogger(__name__)


GUID_PREFIX_BYTES = 12  # RTPS: a participant's GUID prefix; the rest names the endpoint


def participants(gids) -> frozenset:
    """The DDS participants (GUID prefixes) of these endpoint ids."""
    return frozenset(bytes(gid)[:GUID_PREFIX_BYTES] for gid in gids)


@dataclass(frozen=True)
class RobotInfo:
    """A robot as the site's configuration describes it to this gateway."""

    id: int
    name: str
    domain_id: int
    namespace: str
    auto_recover: bool = False

    def owns(self, node_name: str) -> bool:
        return not self.namespace or node_name.startswith(self.namespace.rstrip("/") + "/")


@dataclass(frozen=True)
class NodeSettings:
    """What an operator set for a node in the site: its bring-up position, desired state, and
    whether that state is kept against other tools (protocol.KEEP_POLICIES, or KEEP_PAUSED)."""

    order: int | None = None
    desired_state: str = ""
    keep: str = "off"
    resumed: str = ""  # when an operator last resumed keeping it after a fight (the site's word)


@dataclass
class LiveNode:
    """What the gateway knows of one lifecycle node it has seen."""

    robot: RobotInfo
    name: str
    alive: bool = False  # believed running (as the site shows it)
    gone_reason: str = ""  # why it is not alive: "unreachable", "process_lost" (or "": not watched)
    seen: bool = False  # found in the ROS graph by this gateway run, and subscribed to
    # Set when this run saw the node go and come back, or its process replaced: worth recovering.
    respawned: bool = False
    incarnation: frozenset = frozenset()
    state_id: int = sm.UNKNOWN
    state_read: bool = False  # the state has been read from the node since it appeared
    tracker: TransitionTracker = field(default_factory=TransitionTracker)
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)  # one transition at a time
    last_seen: datetime | None = None
    last_push: asyncio.Future | None = None  # the node's latest live update, so the next one waits for it
    in_transition: bool = False  # a transition of ours is being called (it watches the process)
    # DDS participants (processes) publishing its transition events: the one believed running,
    # and those known to have ended or left (a killed one lingers in the graph for its lease).
    live: frozenset = frozenset()
    departed: frozenset = frozenset()
    process_status: str = ""  # protocol.PROCESS_LOST / "restarted": what was last seen of its process
    process_since: datetime | None = None
    process: str = ""  # the launch profile whose process runs it (process_owners.py), if any

    @property
    def key(self) -> str:
        return protocol.node_key(self.robot.name, self.name)

    def payload(self) -> dict:
        return protocol.node_payload(
            key=self.key,
            robot=self.robot.name,
            name=self.name,
            state_id=self.state_id,
            alive=self.alive,
            gone_reason=self.gone_reason,
            last_seen=self.last_seen.isoformat() if self.last_seen else None,
            process_status=self.process_status,
            process_since=self.process_since.isoformat() if self.process_since else None,
        )

    def groups(self) -> list[str]:
        return [protocol.node_group(self.key), protocol.robot_group(self.robot.id), protocol.FLEET_GROUP]


@dataclass
class StateChange:
    """A node appeared, vanished or moved to another state. ``fact`` is what was reported
    to the site for it (by the stream's reporter, before any listener hears of it)."""

    node: LiveNode
    kind: str  # "seen" | "gone" | "state"
    state_id: int
    respawned: bool = False
    reason: str = ""  # why a node went: "process_lost" (it ended, or left the ROS graph), "unreachable"
    fact: dict | None = None


Listener = Callable[[StateChange], None]


class StateChanges:
    """One stream of state changes. Each is first reported (``report`` returns the fact it
    emitted for the site, kept on the change), then its listeners, side reactions only, are
    called in the order they subscribed, at once and on the gateway's loop: each must be quick
    (hand slow work to a task)."""

    def __init__(self, report: Callable[[StateChange], dict] | None = None) -> None:
        self._report = report
        self._listeners: list[tuple[str, Listener]] = []

    def subscribe(self, name: str, listener: Listener) -> None:
        self._listeners.append((name, listener))

    def publish(self, change: StateChange) -> StateChange:
        if self._report is not None:
            try:
                change.fact = self._report(change)
            except Exception:  # as for a listener: the change still reaches the others
                log.exception("reporting the state change of %s failed", change.node.key)
        for name, listener in self._listeners:
            try:
                listener(change)
            except Exception:  # one listener's bug must not keep the change from the others
                log.exception("state-change listener %s failed on %s", name, change.node.key)
        return change


class NodeRegistry:
    """Robots (from the site's configuration) and the live nodes found in their domains."""

    def __init__(self, changes: StateChanges) -> None:
        self.changes = changes
        self.robots: dict[int, RobotInfo] = {}
        self.settings: dict[int, dict[str, NodeSettings]] = {}  # robot id -> node name -> settings
        self.nodes: dict[tuple[int, str], LiveNode] = {}  # (domain id, fully qualified name) -> node

    # -- robots ---------------------------------------------------------------------
    def robot_for(self, domain_id: int, node_name: str) -> RobotInfo | None:
        """The robot owning a node: same domain, the longest matching namespace."""
        owners = [r for r in self.robots.values() if r.domain_id == domain_id and r.owns(node_name)]
        return max(owners, key=lambda r: len(r.namespace), default=None)

    def robot_named(self, name: str) -> RobotInfo | None:
        return next((r for r in self.robots.values() if r.name == name), None)

    def node_settings(self, robot_id: int, name: str) -> NodeSettings:
        return self.settings.get(robot_id, {}).get(name, NodeSettings())

    def domains(self) -> set[int]:
        return {r.domain_id for r in self.robots.values()}

    # -- nodes ----------------------------------------------------------------------
    def find(self, robot_name: str, node_name: str) -> LiveNode | None:
        for node in self.nodes.values():
            if node.robot.name == robot_name and node.name == node_name:
                return node
        return None

    def of_robot(self, robot_id: int) -> list[LiveNode]:
        return [n for n in self.nodes.values() if n.robot.id == robot_id]

    def alive_count(self) -> int:
        return sum(n.alive for n in self.nodes.values())

    def drop_robot(self, robot_id: int) -> list[tuple[int, LiveNode]]:
        """Forget a robot's nodes (removed, disabled or changed); returns them with their domain."""
        gone = [(k, n) for k, n in self.nodes.items() if n.robot.id == robot_id]
        for key, _node in gone:
            del self.nodes[key]
        return [(key[0], node) for key, node in gone]

    # -- the changes ----------------------------------------------------------------
    def appeared(self, domain_id: int, robot: RobotInfo, name: str, incarnation: frozenset) -> LiveNode:
        node = self.nodes.get((domain_id, name))
        if node is None:
            node = LiveNode(robot=robot, name=name)
            self.nodes[(domain_id, name)] = node
        node.alive, node.seen, node.state_read, node.gone_reason = True, True, False, ""
        node.last_seen = datetime.now(timezone.utc)
        node.tracker = TransitionTracker()
        previous = node.live | node.departed
        node.departed &= participants(incarnation)  # those no longer in the graph need no remembering
        node.live = participants(incarnation) - node.departed
        # Seen before in this run and back with another process (or with none known yet): a new
        # instance. Back with the same one (it answers again after it was unreachable): not, unless
        # a new instance seen before it went has not had its state read yet.
        node.respawned = node.respawned or (
            node.incarnation != frozenset() and (not node.live or bool(node.live - previous)))
        node.incarnation = incarnation
        self.changes.publish(StateChange(node, "seen", node.state_id))
        return node

    def vanished(self, node: LiveNode, reason: str = "", *, ended: bool = False) -> StateChange:
        """The node is gone. ``ended``: its process is known dead (it may linger in the graph
        until its DDS lease runs out, and is not taken back meanwhile); a node that merely left
        the graph is taken back if the same process shows up again."""
        node.alive, node.seen, node.last_seen = False, False, datetime.now(timezone.utc)
        node.gone_reason = reason
        if reason == protocol.PROCESS_LOST:
            node.process_status, node.process_since = "lost", node.last_seen
        if ended:
            node.departed |= node.live
        return self.changes.publish(StateChange(node, "gone", node.state_id, reason=reason))

    def set_state(self, node: LiveNode, state_id: int, *, read: bool = False) -> StateChange | None:
        """The node is now in ``state_id``; returns the change, or None if it is no news.
        ``read``: the state was just read from the node (the first read after it appeared
        is what recovery waits for)."""
        respawned = False
        if read:
            node.state_read = True
            # A new instance is announced (and recovered) once it is alive: a read that ends
            # after the node was called gone (unreachable meanwhile) leaves that for the read
            # after it is back.
            if node.alive:
                respawned, node.respawned = node.respawned, False
        if state_id == node.state_id and not respawned:
            return None
        node.state_id = state_id
        node.last_seen = datetime.now(timezone.utc)
        if respawned:  # the first state of a new instance of its process
            node.process_status, node.process_since = "restarted", node.last_seen
        return self.changes.publish(StateChange(node, "state", state_id, respawned=respawned))
