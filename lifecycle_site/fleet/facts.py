"""What gateways report, written to the database: the one place that does it.

``apply_facts`` is called by the ingest process for every fact it reads from a gateway's
stream, and by the request path for the facts that come back with a reply (so the audit
record exists before the user has the answer). Applying a fact twice has the effect of
applying it once: audit records are keyed by the fact's id, states carry their time.
Fact shapes: ros_gateway/shared/protocol.py and the wire contract in docs/architecture.md.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any, Iterable

from asgiref.sync import async_to_sync
from channels.layers import get_channel_layer
from django.contrib.auth import get_user_model
from django.db import IntegrityError, InterfaceError, OperationalError, transaction
from django.db.models import Q
from django.db.models.functions import Coalesce

from lifecycle_site.audit.models import ParameterRecord, TransitionRecord
from lifecycle_site.fleet.models import GroupRun, ManagedNode, Robot
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm

log = logging.getLogger(__name__)
# Why a node.gone fact says a node went (ros_gateway/liveness.py); anything else counts as "".
GONE_REASONS = ("unreachable",)

DONE = (GroupRun.Status.SUCCEEDED, GroupRun.Status.FAILED, GroupRun.Status.PARTIAL)


class FactRejected(ValueError):
    """A fact the site cannot apply (malformed, or about what its gateway does not own)."""


@dataclass
class Applied:
    """What applying a list of facts did."""

    transitions: dict[str, TransitionRecord] = field(default_factory=dict)  # by fact id, made now or before
    parameters: dict[str, ParameterRecord] = field(default_factory=dict)
    created: list[TransitionRecord] = field(default_factory=list)  # made by this call (pages get them)
    rejected: int = 0

    def transition_record(self, facts: Iterable[dict]) -> TransitionRecord | None:
        """The audit record of the (first) transition fact among ``facts``."""
        for fact in facts:
            if isinstance(fact, dict) and fact.get("type") == protocol.TRANSITION:
                return self.transitions.get(str(fact.get("id")))
        return None


def parse_time(value: Any, what: str = "time") -> datetime:
    """An ISO-8601 time as an aware datetime (UTC when it carries no offset)."""
    try:
        moment = datetime.fromisoformat(str(value))
    except ValueError:
        raise FactRejected(f"{what} {value!r} is not an ISO-8601 time") from None
    return moment if moment.tzinfo else moment.replace(tzinfo=timezone.utc)


def optional_time(value: Any, what: str) -> datetime | None:
    return None if value in (None, "") else parse_time(value, what)


class _Gateway:
    """One gateway's robots and nodes, read once per call and kept while its facts are applied."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.robots = {r.name: r for r in Robot.objects.filter(gateway__name=name).select_related("gateway")}
        self.nodes: dict[int, dict[str, ManagedNode | None]] = {}  # None: known not to exist

    def prefetch(self, facts: list) -> None:
        """Read the nodes the facts name, in one query (not all nodes of their robots: a
        reply's three facts on a robot of 100 nodes read 1 node, not 100)."""
        wanted: dict[int, set[str]] = {}
        for fact in facts:
            if isinstance(fact, dict) and isinstance(fact.get("node"), str):
                robot = self.robots.get(fact.get("robot"))
                if robot is not None:
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

    def robot(self, fact: dict, required: bool = True) -> Robot | None:
        """The fact's robot; it must be one of this gateway's. ``required=False`` allows a robot
        that no longer exists (its audit records are still kept, by name)."""
        name = fact.get("robot")
        robot = self.robots.get(name)
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


def apply_facts(gateway: str, facts: Iterable[dict]) -> Applied:
    """Apply a gateway's facts in order, in one transaction; a fact that cannot be applied is
    logged, counted in ``rejected`` and skipped (the others still are)."""
    applied = Applied()
    with transaction.atomic():
        facts = list(facts)
        known = _Gateway(gateway)
        known.prefetch(facts)
        for fact in facts:
            try:
                with transaction.atomic():  # a savepoint: a fact that fails, fails alone
                    apply_fact(known, fact, applied)
            except (OperationalError, InterfaceError):
                raise  # the database itself is unavailable: the whole batch is tried again
            except Exception as exc:  # noqa: BLE001 - whatever a malformed fact causes, it must not block the rest
                applied.rejected += 1
                known.nodes.clear()  # what the failed fact created is gone
                kind = fact.get("type") if isinstance(fact, dict) else type(fact).__name__
                log.warning("gateway %s: skipped a %s fact that cannot be applied: %s: %s", gateway, kind,
                            type(exc).__name__, exc)
    return applied


def apply_fact(known: _Gateway, fact: dict, applied: Applied) -> None:
    if not isinstance(fact, dict):
        raise FactRejected("a fact must be a JSON object")
    if fact.get("gateway") != known.name:
        raise FactRejected(f"it names gateway {fact.get('gateway')!r}, but came from {known.name}")
    kind = fact.get("type")
    handler = HANDLERS.get(kind)
    if handler is None:
        raise FactRejected(f"unknown fact type {kind!r}")
    handler(known, fact, parse_time(fact.get("at"), "at"), applied)


def _node_seen(known: _Gateway, fact: dict, at: datetime, applied: Applied) -> None:
    robot = known.robot(fact)
    node = known.node(robot, fact["node"])
    if node is None:
        known.new_node(robot, fact["node"], at)
        return
    ManagedNode.objects.filter(pk=node.pk).update(alive=True, gone_reason="", last_seen=at,
                                                  first_seen=Coalesce("first_seen", at))


def _node_gone(known: _Gateway, fact: dict, at: datetime, applied: Applied) -> None:
    robot = known.robot(fact)
    node = known.node(robot, fact["node"])
    if node is not None:
        reason = fact.get("reason") if fact.get("reason") in GONE_REASONS else ""
        ManagedNode.objects.filter(pk=node.pk).update(alive=False, gone_reason=reason, last_seen=at)


def _node_state(known: _Gateway, fact: dict, at: datetime, applied: Applied) -> None:
    robot = known.robot(fact)
    state_id = int(fact["state_id"])
    changes = {"state_id": state_id, "state_label": sm.state_label(state_id), "state_changed": at}
    node = known.node(robot, fact["node"])
    if node is None:
        known.new_node(robot, fact["node"], at, **changes)
        return
    # Applied twice or late (the request path and the ingest process both apply a reply's
    # facts), an older state never overwrites a newer one.
    ManagedNode.objects.filter(pk=node.pk).filter(Q(state_changed__isnull=True) | Q(state_changed__lte=at)).update(
        last_seen=at, **changes
    )


def _robot_nodes(known: _Gateway, fact: dict, at: datetime, applied: Applied) -> None:
    robot = known.robot(fact)
    listed = fact["nodes"]
    if not isinstance(listed, list) or not all(isinstance(n, str) for n in listed):
        raise FactRejected("nodes must be a list of node names")
    ManagedNode.objects.filter(robot=robot).exclude(name__in=listed).update(alive=False)
    ManagedNode.objects.filter(robot=robot, name__in=listed).update(
        alive=True, gone_reason="", last_seen=at, first_seen=Coalesce("first_seen", at)
    )
    known.load_robot(robot)
    for name in listed:  # a node.seen that was lost on the way
        if known.node(robot, name) is None:
            known.new_node(robot, name, at)


def _user_id(value: Any) -> int | None:
    if value is None:
        return None
    user_id = int(value)
    return user_id if get_user_model().objects.filter(pk=user_id).exists() else None


def _label(state_id: int | None) -> str:
    return "" if state_id is None else sm.state_label(state_id)


def _optional_int(value: Any) -> int | None:
    return None if value is None else int(value)


def _transition(known: _Gateway, fact: dict, at: datetime, applied: Applied) -> None:
    fact_id = str(fact["id"])
    existing = TransitionRecord.objects.select_related("node").filter(fact_id=fact_id).first()
    if existing is not None:
        applied.transitions[fact_id] = existing
        return
    robot = known.robot(fact, required=False)
    node = known.node(robot, fact["node"]) if robot else None
    transition_id = _optional_int(fact.get("transition_id"))
    start, result = _optional_int(fact.get("start_state")), _optional_int(fact.get("result_state"))
    goal = sm.SUCCESS_GOAL.get(transition_id) if transition_id is not None else None
    requested_at = parse_time(fact["requested_at"], "requested_at")
    completed_at = optional_time(fact.get("completed_at"), "completed_at")
    outcome, source = fact["outcome"], fact["source"]
    if outcome not in TransitionRecord.Outcome.values or source not in TransitionRecord.Source.values:
        raise FactRejected(f"outcome {outcome!r} or source {source!r} is not one the audit log knows")
    record = TransitionRecord(
        fact_id=fact_id,
        node=node,
        robot=robot,
        robot_name=str(fact["robot"]),
        node_name=str(fact["node"]),
        transition_id=transition_id,
        transition_label=str(fact.get("transition_label") or ""),
        start_state_id=start,
        start_state_label=_label(start),
        goal_state_id=goal,
        goal_state_label=_label(goal),
        result_state_id=result,
        result_state_label=_label(result),
        outcome=outcome,
        source=source,
        requested_by_id=_user_id(fact.get("user_id")),
        requested_at=requested_at,
        completed_at=completed_at,
        duration_ms=round((completed_at - requested_at).total_seconds() * 1000, 2) if completed_at else None,
        error=str(fact.get("error") or ""),
        run_id=str(fact.get("run_id") or ""),
    )
    try:
        with transaction.atomic():
            record.save()
    except IntegrityError:  # applied meanwhile by another process
        record = TransitionRecord.objects.select_related("node").get(fact_id=fact_id)
    else:
        applied.created.append(record)
    applied.transitions[fact_id] = record


def _parameter(known: _Gateway, fact: dict, at: datetime, applied: Applied) -> None:
    fact_id = str(fact["id"])
    existing = ParameterRecord.objects.filter(fact_id=fact_id).first()
    if existing is not None:
        applied.parameters[fact_id] = existing
        return
    robot = known.robot(fact, required=False)
    outcome, source = fact["outcome"], fact["source"]
    if outcome not in ("succeeded", "rejected", "observed") or source not in TransitionRecord.Source.values:
        raise FactRejected(f"outcome {outcome!r} or source {source!r} is not one the audit log knows")
    record = ParameterRecord(
        fact_id=fact_id,
        node=known.node(robot, fact["node"]) if robot else None,
        robot_name=str(fact["robot"]),
        node_name=str(fact["node"]),
        name=str(fact["name"]),
        old_value=fact.get("old"),
        new_value=fact.get("new"),
        outcome=outcome,
        reason=str(fact.get("reason") or ""),
        source=source,
        requested_by_id=_user_id(fact.get("user_id")),
        at=at,
    )
    try:
        with transaction.atomic():
            record.save()
    except IntegrityError:
        record = ParameterRecord.objects.get(fact_id=fact_id)
    applied.parameters[fact_id] = record


def _run(known: _Gateway, fact: dict, at: datetime, applied: Applied) -> None:
    run_id = str(fact["run_id"])
    status = fact["status"]
    if status not in GroupRun.Status.values:
        raise FactRejected(f"run status {status!r} is unknown")
    changes: dict[str, Any] = {"status": status}
    for name in ("message", "results"):
        if name in fact:
            changes[name] = fact[name] if name == "results" else str(fact[name] or "")
    for name in ("started", "finished"):
        if fact.get(name):
            changes[name] = parse_time(fact[name], name)
    run = GroupRun.objects.select_for_update().select_related("robot").filter(pk=run_id).first()
    if run is None:
        if "operation" not in fact:
            raise FactRejected(f"there is no run {run_id}")
        robot = known.robot(fact)
        GroupRun.objects.create(
            id=run_id, robot=robot, operation=fact["operation"], only_nodes=fact.get("only_nodes") or [],
            source=str(fact.get("source") or "recovery"), policy=fact.get("policy") or GroupRun.Policy.STOP,
            node_timeout=float(fact.get("node_timeout") or 5.0), **changes,
        )
        return
    if run.robot.name not in known.robots:
        raise FactRejected(f"run {run_id} is for robot {run.robot.name}, not one of gateway {known.name}'s")
    if run.status in DONE and status not in DONE:
        return  # a late progress report of a run that is over
    GroupRun.objects.filter(pk=run_id).update(**changes)


def _gateway_started(known: _Gateway, fact: dict, at: datetime, applied: Applied) -> None:
    message = (f"the gateway {known.name} restarted while it ran (instance {fact.get('instance', '?')}); "
               "its last results are kept")
    GroupRun.objects.filter(
        robot__gateway__name=known.name, status__in=(GroupRun.Status.QUEUED, GroupRun.Status.RUNNING), created__lt=at
    ).update(status=GroupRun.Status.FAILED, message=message, finished=at)


HANDLERS = {
    protocol.NODE_SEEN: _node_seen,
    protocol.NODE_GONE: _node_gone,
    protocol.NODE_STATE: _node_state,
    protocol.ROBOT_NODES: _robot_nodes,
    protocol.TRANSITION: _transition,
    protocol.PARAMETER: _parameter,
    protocol.RUN: _run,
    protocol.GATEWAY_STARTED: _gateway_started,
}


# --- telling the pages -----------------------------------------------------------------------

def record_messages(records: Iterable[TransitionRecord]) -> list[tuple[str, dict]]:
    """The node pages' live audit rows for new records: (group, message) pairs."""
    return [
        (protocol.node_group(record.node.key), {"type": "audit.record", "record": record.as_dict()})
        for record in records
        if record.node_id is not None and record.node is not None
    ]


# Live updates sent side by side (fewer than the channel layer's Redis pool of 100 connections).
PUSH_CONCURRENCY = 50


def push(messages: list[tuple[str, dict]]) -> None:
    """Send (group, message) pairs to the Channels layer; a failure is logged, never raised
    (what was stored is there for the next page load)."""
    if not messages:
        return
    layer = get_channel_layer()
    if layer is None:
        return

    async def send_all() -> list:
        import asyncio

        # A few at a time: the channel layer's Redis pool holds at most 100 connections, and a
        # group_send beyond them fails ("Too many connections"), losing its message.
        results: list = []
        for start in range(0, len(messages), PUSH_CONCURRENCY):
            chunk = messages[start : start + PUSH_CONCURRENCY]
            results += await asyncio.gather(*(layer.group_send(g, m) for g, m in chunk), return_exceptions=True)
        return results

    try:
        failures = [r for r in async_to_sync(send_all)() if isinstance(r, Exception)]
    except Exception as exc:  # noqa: BLE001 - the channel layer's errors are many; none must stop us
        failures = [exc]
    if failures:
        log.warning("could not push %d of %d live updates: %s", len(failures), len(messages), failures[0])
