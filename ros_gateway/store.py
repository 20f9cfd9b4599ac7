"""The facts the gateway writes to the database (Django ORM, called from one DB thread)."""
from __future__ import annotations

import os
import socket
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import NamedTuple

from asgiref.sync import sync_to_async
from django.db import connection, transaction
from django.db.models import Count
from django.utils import timezone

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import GatewayHeartbeat, LogRecord, ManagedNode, Robot
from ros_gateway.shared import state_machine as sm


def db(func):
    """Run an ORM function on the single database thread (one writer: no lock contention)."""
    return sync_to_async(func, thread_sensitive=True)


@dataclass(frozen=True)
class RobotInfo:
    id: int
    name: str
    domain_id: int
    namespace: str
    auto_recover: bool = False

    def owns(self, node_name: str) -> bool:
        return not self.namespace or node_name.startswith(self.namespace.rstrip("/") + "/")


@dataclass
class NodeRow:
    id: int
    key: str
    state_id: int
    alive: bool


def load_robots() -> list[RobotInfo]:
    return [
        RobotInfo(r.id, r.name, r.domain_id, r.namespace, r.auto_recover)
        for r in Robot.objects.filter(enabled=True).only("id", "name", "domain_id", "namespace", "auto_recover")
    ]


def load_nodes(robot_id: int) -> dict[str, NodeRow]:
    return {
        n.name: NodeRow(n.id, n.key, n.state_id, n.alive)
        for n in ManagedNode.objects.filter(robot_id=robot_id).only("id", "name", "key", "state_id", "alive")
    }


def node_seen(robot_id: int, name: str) -> NodeRow:
    """Mark a node alive (creating it on first sight)."""
    now = timezone.now()
    node, created = ManagedNode.objects.select_related("robot").get_or_create(
        robot_id=robot_id, name=name, defaults={"alive": True, "first_seen": now, "last_seen": now}
    )
    if not created:
        node.alive = True
        node.last_seen = now
        if node.first_seen is None:
            node.first_seen = now
        node.save(update_fields=["alive", "last_seen", "first_seen"])
    return NodeRow(node.id, node.key, node.state_id, True)


def desired_state(node_id: int) -> str:
    return ManagedNode.objects.filter(id=node_id).values_list("desired_state", flat=True).first() or ""


def nodes_lost(node_ids: list[int]) -> None:
    ManagedNode.objects.filter(id__in=node_ids).update(alive=False, last_seen=timezone.now())


def nodes_still_alive(node_ids: list[int]) -> None:
    ManagedNode.objects.filter(id__in=node_ids).update(last_seen=timezone.now())


def save_state(node_id: int, state_id: int) -> None:
    now = timezone.now()
    ManagedNode.objects.filter(id=node_id).update(
        state_id=state_id, state_label=sm.state_label(state_id), state_changed=now, last_seen=now
    )


def record_transition(
    *,
    node_id: int | None,
    robot: RobotInfo,
    node_name: str,
    transition: sm.Transition | None,
    start_state: int | None,
    result_state: int | None,
    outcome: str,
    source: str,
    requested_at: datetime,
    completed_at: datetime | None,
    user_id: int | None = None,
    error: str = "",
    run_id: str = "",
    requested_label: str = "",
    node_key: str = "",
) -> dict:
    """Append one audit record; returns it as the API shows it."""

    def label(state_id: int | None) -> str:
        return "" if state_id is None else sm.state_label(state_id)

    goal = sm.SUCCESS_GOAL.get(transition.id) if transition else None
    duration = round((completed_at - requested_at).total_seconds() * 1000, 2) if completed_at else None
    record = TransitionRecord.objects.create(
        node_id=node_id,
        robot_id=robot.id,
        robot_name=robot.name,
        node_name=node_name,
        transition_id=transition.id if transition else None,
        # What was asked for stays readable even when it named no valid transition.
        transition_label=transition.label if transition else requested_label,
        start_state_id=start_state,
        start_state_label=label(start_state),
        goal_state_id=goal,
        goal_state_label=label(goal),
        result_state_id=result_state,
        result_state_label=label(result_state),
        outcome=outcome,
        source=source,
        requested_by_id=user_id,
        requested_at=requested_at,
        completed_at=completed_at,
        duration_ms=duration,
        error=error,
        run_id=run_id,
    )
    if node_id is not None and node_key:
        record.node = ManagedNode(pk=node_id, key=node_key)  # what as_dict needs, without a query
    return record.as_dict()


class LogRow(NamedTuple):
    """One log record to store, as plain data: LogRecord's columns, in this order."""

    robot_id: int
    node_id: int | None
    logger: str
    stamp: datetime  # timezone-aware
    level: int
    message: str
    file: str
    function: str
    line: int


def insert_logs(rows: list[LogRow]) -> list[int]:
    """Store log records in one transaction; returns their ids, in the order of ``rows``.

    On SQLite the rows go in as plain tuples through one ``executemany``: ``bulk_create``
    spends most of its time compiling the SQL field by field and row by row. The first row's
    INSERT lets AUTOINCREMENT choose its id (never reusing a pruned one) and takes the write
    lock before anything is read, so no other writer can come in before the commit. The other
    rows get the ids that follow, written explicitly: the ids returned are the ids stored, and
    a clash would fail the batch rather than push wrong ids. (Python's sqlite3 returns no rows
    from ``executemany`` with ``RETURNING``.) Other databases (PostgreSQL) use ``bulk_create``,
    which returns the ids there.
    """
    if not rows:
        return []
    if connection.vendor != "sqlite":
        return _insert_logs_orm(rows)
    params = [(*row[:3], _stamp_for_db(row[3]), *row[4:]) for row in rows]
    table = connection.ops.quote_name(LogRecord._meta.db_table)
    columns = [connection.ops.quote_name(LogRecord._meta.get_field(name).column) for name in LogRow._fields]
    values = ", ".join(["%s"] * len(columns))
    pk = connection.ops.quote_name(LogRecord._meta.pk.column)
    with transaction.atomic(), connection.cursor() as cursor:
        cursor.execute(f"INSERT INTO {table} ({', '.join(columns)}) VALUES ({values})", params[0])
        first = cursor.lastrowid
        if len(params) > 1:
            cursor.executemany(
                f"INSERT INTO {table} ({pk}, {', '.join(columns)}) VALUES (%s, {values})",
                [(first + i, *row) for i, row in enumerate(params[1:], start=1)],
            )
    return list(range(first, first + len(rows)))


def _stamp_for_db(stamp: datetime):
    """The stamp exactly as the ORM stores it (``DateTimeField.get_db_prep_save``). For an aware
    datetime that comes down to ``adapt_datetimefield_value`` (UTC text on SQLite), called
    directly: the field's checks around it add about 10% to insert_logs. Anything else takes
    the field's own path (a naive datetime is made aware, with Django's warning)."""
    if isinstance(stamp, datetime) and timezone.is_aware(stamp):
        return connection.ops.adapt_datetimefield_value(stamp)
    return LogRecord._meta.get_field("stamp").get_db_prep_save(stamp, connection)


def _insert_logs_orm(rows: list[LogRow]) -> list[int]:
    saved = LogRecord.objects.bulk_create([LogRecord(**row._asdict()) for row in rows], batch_size=500)
    return [record.id for record in saved]


def prune_logs(keep_per_logger: int, keep_hours: float) -> int:
    """Delete records older than the age limit and beyond the per-logger count."""
    deleted, _ = LogRecord.objects.filter(stamp__lt=timezone.now() - timedelta(hours=keep_hours)).delete()
    crowded = (
        LogRecord.objects.values("robot_id", "logger")
        .annotate(n=Count("id"))
        .filter(n__gt=keep_per_logger)
    )
    for group in crowded:
        per_logger = LogRecord.objects.filter(robot_id=group["robot_id"], logger=group["logger"])
        cutoff = per_logger.order_by("-id").values_list("id", flat=True)[keep_per_logger - 1]
        count, _ = per_logger.filter(id__lt=cutoff).delete()
        deleted += count
    return deleted


def heartbeat(name: str, started: datetime, domains: list[int]) -> None:
    with transaction.atomic():
        GatewayHeartbeat.objects.update_or_create(
            name=name,
            defaults={
                "hostname": socket.gethostname(),
                "pid": os.getpid(),
                "started": started,
                "last_beat": timezone.now(),
                "watched_domains": sorted(domains),
            },
        )


def running_twin(name: str, fresh_within: float) -> str | None:
    """Describe another live gateway of the same name, if any (two would record everything twice)."""
    limit = timezone.now() - timedelta(seconds=fresh_within)
    other = GatewayHeartbeat.objects.filter(name=name, last_beat__gte=limit).first()
    if other is None or (other.pid == os.getpid() and other.hostname == socket.gethostname()):
        return None
    return f"pid {other.pid} on {other.hostname}, last heartbeat {other.last_beat:%H:%M:%S}"


def gateway_stopped(name: str) -> None:
    """A clean stop says so at once instead of letting the heartbeat go stale."""
    GatewayHeartbeat.objects.filter(name=name).delete()
