"""What applying one batch of a gateway's facts knows and produces (ingest.facts): the gateway's
robots, the nodes and users the facts name, each read once per batch (or handed over by the
request path as hints), and what the batch did."""
from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime
from typing import Any, Iterable

from django.contrib.auth import get_user_model
from django.db import IntegrityError, transaction
from django.db.models import Q

from lifecycle_site.audit.models import ParameterRecord, ProcessRecord, TransitionRecord
from lifecycle_site.fleet.models import ManagedNode, Robot
from lifecycle_site.gateway_link.gateway_input import FactRejected
from ros_gateway.shared import protocol


@dataclass
class Applied:
    """What applying a list of facts did."""

    transitions: dict[str, TransitionRecord] = field(default_factory=dict)  # by fact id, made now or before
    parameters: dict[str, ParameterRecord] = field(default_factory=dict)
    created: list[TransitionRecord] = field(default_factory=list)  # made by this call (pages get them)
    created_parameters: list[ParameterRecord] = field(default_factory=list)  # made by this call
    created_processes: list[ProcessRecord] = field(default_factory=list)  # made by this call
    accepted: list[dict] = field(default_factory=list)  # the facts applied (not rejected), in order
    pushes: list[tuple[str, dict]] = field(default_factory=list)  # for open pages, once committed
    rejected: int = 0

    def transition_record(self, facts: Iterable[dict]) -> TransitionRecord | None:
        """The audit record of the (first) transition fact among ``facts``."""
        for fact in facts:
            if isinstance(fact, dict) and fact.get("type") == protocol.TRANSITION:
                return self.transitions.get(str(fact.get("id")))
        return None


@dataclass
class Hints:
    """What the request path already holds: the node a reply is about (with its robot and
    gateway) and the user who asked, so applying the reply's facts need not read them again."""

    node: ManagedNode | None = None
    user: Any = None


class KnownRecords:
    """One gateway's robots and nodes, read once per call and kept while its facts are applied."""

    def __init__(self, name: str, hints: Hints | None = None, isolated: bool = True) -> None:
        self.name = name
        self.isolated = isolated  # each fact in a savepoint of its own
        self.robots: dict[str, Robot] = {}
        self.all_robots = False  # every robot of the gateway read (else only the hinted one)
        self.nodes: dict[int, dict[str, ManagedNode | None]] = {}  # None: known not to exist
        self.usernames: dict[int, str | None] = {}  # None: no such user
        self.stored: set[str] = set()  # fact ids of the batch's audit records stored before it
        node = hints.node if hints else None
        if node is not None and node.robot.gateway.name == name:
            self.robots[node.robot.name] = node.robot
            self.nodes[node.robot_id] = {node.name: node}
        else:
            self.load_robots()
        user = hints.user if hints else None
        if user is not None and user.pk is not None:
            self.usernames[user.pk] = user.get_username()

    def load_robots(self) -> None:
        self.robots = {r.name: r for r in Robot.objects.filter(gateway__name=self.name).select_related("gateway")}
        self.all_robots = True

    def owns(self, robot_name: object) -> bool:
        if not isinstance(robot_name, str):
            return False
        if robot_name not in self.robots and not self.all_robots:
            self.load_robots()
        return robot_name in self.robots

    def username(self, user_id: int) -> str | None:
        """The user's name, or None when there is no such user (deleted since)."""
        if user_id not in self.usernames:
            found = get_user_model().objects.filter(pk=user_id).values_list(get_user_model().USERNAME_FIELD)
            self.usernames[user_id] = next((name for (name,) in found), None)
        return self.usernames[user_id]

    def prefetch(self, facts: list) -> None:
        """Read the nodes the facts name, in one query (not all nodes of their robots: a
        reply's three facts on a robot of 100 nodes read 1 node, not 100); and which of their
        audit records are stored already (the request path and the ingest process both apply
        a reply's facts), one query per kind of record."""
        self._find_stored(facts)
        wanted: dict[int, set[str]] = {}
        for fact in facts:
            if isinstance(fact, dict) and isinstance(fact.get("node"), str) and self.owns(fact.get("robot")):
                robot = self.robots[fact["robot"]]
                if fact["node"] not in self.nodes.get(robot.id, {}):
                    wanted.setdefault(robot.id, set()).add(fact["node"])
        if not wanted:
            return
        query = Q()
        for robot_id, names in wanted.items():
            query |= Q(robot_id=robot_id, name__in=names)
            known = self.nodes.setdefault(robot_id, {})
            for name in names:
                known.setdefault(name, None)
        for node in ManagedNode.objects.filter(query):
            self.nodes[node.robot_id][node.name] = node

    def _find_stored(self, facts: list) -> None:
        ids: dict[str, list[str]] = {protocol.TRANSITION: [], protocol.PARAMETER: [], protocol.PROCESS: []}
        for fact in facts:
            if isinstance(fact, dict) and fact.get("type") in ids:
                ids[fact["type"]].append(str(fact.get("id")))
        for kind, model in ((protocol.TRANSITION, TransitionRecord), (protocol.PARAMETER, ParameterRecord),
                            (protocol.PROCESS, ProcessRecord)):
            if ids[kind]:
                found = model.objects.filter(fact_id__in=ids[kind]).order_by().values_list("fact_id", flat=True)
                self.stored.update(found)

    def robot(self, fact: dict, required: bool = True) -> Robot | None:
        """The fact's robot; it must be one of this gateway's. ``required=False`` allows a robot
        that no longer exists (its audit records are still kept, by name)."""
        name = fact.get("robot")
        robot = self.robots.get(name) if self.owns(name) else None
        if robot is None and (required or Robot.objects.filter(name=name).exists()):
            raise FactRejected(f"robot {name!r} is not one of gateway {self.name}'s robots")
        return robot

    def load_robot(self, robot: Robot) -> None:
        """Every node of the robot (for a fact about all of them)."""
        known = self.nodes.setdefault(robot.id, {})
        known.update({n.name: n for n in ManagedNode.objects.filter(robot=robot)})

    def node(self, robot: Robot, name: str) -> ManagedNode | None:
        known = self.nodes.setdefault(robot.id, {})
        if name not in known:
            known[name] = ManagedNode.objects.filter(robot=robot, name=name).first()
        node = known[name]
        if node is not None:
            node.robot = robot  # as_dict and key need no query
        return node

    def new_node(self, robot: Robot, name: str, at: datetime, **fields: Any) -> ManagedNode:
        if not name.startswith("/"):
            raise FactRejected(f"{name!r} is not a fully qualified node name")
        node, _ = ManagedNode.objects.get_or_create(
            robot=robot, name=name, defaults={"alive": True, "first_seen": at, "last_seen": at, **fields}
        )
        self.nodes.setdefault(robot.id, {})[name] = node
        node.robot = robot
        return node


def save_once(known: KnownRecords, record: TransitionRecord | ParameterRecord | ProcessRecord) -> bool:
    """Save an audit record unless one with its fact id was saved meanwhile by another process
    (the request path and the ingest process both apply a reply's facts): False then. Outside
    isolated mode that race fails the batch, which is then applied again isolated."""
    if not known.isolated:
        record.save()
        return True
    try:
        with transaction.atomic():
            record.save()
    except IntegrityError:
        return False
    return True
