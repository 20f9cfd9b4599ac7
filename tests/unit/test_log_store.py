"""Log records written as plain tuples (store.insert_logs) read back through the ORM exactly as
if the ORM had written them, with the ids the live push sends."""
from __future__ import annotations

from datetime import datetime, timedelta, timezone
from types import SimpleNamespace

import pytest
from asgiref.sync import async_to_sync
from django.db import IntegrityError, connection
from django.utils import timezone as dj_timezone

from lifecycle_site.fleet.models import LogRecord, ManagedNode, Robot
from ros_gateway import store
from ros_gateway.logs import LogPipeline
from ros_gateway.shared import protocol
from ros_gateway.store import LogRow
from ros_gateway.streams import LogEntry

COLUMNS = ["id", *(LogRecord._meta.get_field(name).column for name in LogRow._fields)]


@pytest.fixture
def robot(db):
    robot = Robot.objects.create(name="store-agv", domain_id=77, namespace="")
    node = ManagedNode.objects.create(robot=robot, name="/scanner", key="store-agv.scanner")
    return robot, node


def sample_rows(robot: Robot, node: ManagedNode, count: int) -> list[LogRow]:
    plus_two = timezone(timedelta(hours=2))
    base = datetime(2026, 3, 29, 0, 59, 59, 999_999, tzinfo=timezone.utc)  # around a DST change in Europe
    rows = []
    for i in range(count):
        stamp = base + timedelta(microseconds=7 * i, seconds=i)
        rows.append(LogRow(
            robot.id,
            node.id if i % 3 else None,
            f"scanner.sub{i % 4}",
            stamp.astimezone(plus_two) if i % 5 == 0 else stamp,  # any aware datetime is stored as UTC
            (10, 20, 30, 40, 50)[i % 5],
            f"line {i}: ünïcödé ✓ 'quotes' \"and\" %s %(x)s ?" + "x" * (i % 7),
            "" if i % 2 else "/src/scanner.cpp",
            "scan_cb",
            i,
        ))
    return rows


def raw(ids: list[int]) -> list[tuple]:
    with connection.cursor() as cursor:
        cursor.execute(
            f"SELECT {', '.join(COLUMNS)} FROM fleet_logrecord WHERE id IN ({', '.join(['%s'] * len(ids))}) "
            "ORDER BY id",
            ids,
        )
        return cursor.fetchall()


def test_rows_read_back_through_the_orm_equal_to_what_was_written(robot):
    rows = sample_rows(*robot, 50)
    ids = store.insert_logs(rows)
    assert len(ids) == len(set(ids)) == 50
    assert ids == sorted(ids)
    stored = {record.id: record for record in LogRecord.objects.filter(id__in=ids)}
    assert set(stored) == set(ids)
    for row, row_id in zip(rows, ids, strict=True):
        record = stored[row_id]
        assert dj_timezone.is_aware(record.stamp)
        assert record.stamp == row.stamp
        assert tuple(getattr(record, name) for name in LogRow._fields) == row


def test_stored_exactly_as_bulk_create_stores_them(robot):
    rows = sample_rows(*robot, 30)
    fast = raw(store.insert_logs(rows))
    orm = raw(store._insert_logs_orm(rows))
    assert [r[1:] for r in fast] == [r[1:] for r in orm]  # every column byte for byte, but the id
    assert {type(r[4]) for r in fast} == {type(r[4]) for r in orm}


def test_the_orm_fallback_returns_the_stored_ids_too(robot):
    rows = sample_rows(*robot, 7)
    ids = store._insert_logs_orm(rows)
    assert [tuple(getattr(r, n) for n in LogRow._fields) for r in LogRecord.objects.filter(id__in=ids).order_by("id")] \
        == rows


def test_queries_of_the_site_and_pruning_work_on_the_rows(robot):
    robot_row, node = robot
    now = dj_timezone.now()
    old = LogRow(robot_row.id, node.id, "scanner", now - timedelta(hours=30), 40, "old", "", "", 1)
    new = LogRow(robot_row.id, node.id, "scanner", now - timedelta(minutes=5), 20, "new", "", "", 2)
    old_id, new_id = store.insert_logs([old, new])
    assert list(LogRecord.objects.filter(stamp__lt=now - timedelta(hours=1)).values_list("id", flat=True)) == [old_id]
    assert list(LogRecord.objects.filter(node=node, level__gte=40).values_list("id", flat=True)) == [old_id]
    assert LogRecord.objects.filter(stamp__date=new.stamp.date()).filter(id=new_id).exists()
    assert LogRecord.objects.filter(robot=robot_row).first().id == new_id  # "-id" ordering: newest first
    assert store.prune_logs(keep_per_logger=100, keep_hours=24) == 1
    assert list(LogRecord.objects.values_list("id", flat=True)) == [new_id]


def test_ids_follow_on_and_are_never_reused(robot):
    rows = sample_rows(*robot, 5)
    first = store.insert_logs(rows)
    assert first == list(range(first[0], first[0] + 5))
    LogRecord.objects.filter(id__in=first[2:]).delete()  # the newest ids gone (as a prune could do)
    second = store.insert_logs(rows[:1]) + store.insert_logs(rows)
    assert second == list(range(first[-1] + 1, first[-1] + 7))
    # The ORM's own next insert continues after them: AUTOINCREMENT's sequence was advanced.
    orm = LogRecord.objects.create(**rows[0]._asdict())
    assert orm.id == second[-1] + 1
    assert store.insert_logs([]) == []


@pytest.mark.django_db(transaction=True)
def test_a_batch_is_one_transaction():
    robot = Robot.objects.create(name="store-agv-tx", domain_id=78)
    rows = [LogRow(robot.id, None, "a", dj_timezone.now(), 20, "ok", "", "", 0)] * 3
    rows.append(LogRow(robot.id + 1000, None, "a", dj_timezone.now(), 20, "no such robot", "", "", 0))
    with pytest.raises(IntegrityError):
        store.insert_logs(rows)
    assert not LogRecord.objects.exists()
    assert len(store.insert_logs(rows[:3])) == 3


class FakeRelay:
    def __init__(self) -> None:
        self.sent: list[tuple[list[str], dict]] = []

    async def publish(self, groups: list[str], message: dict) -> None:
        self.sent.append((groups, message))


def fake_gateway(robot: Robot, node: ManagedNode, buffer: int = 100) -> SimpleNamespace:
    info = store.RobotInfo(robot.id, robot.name, robot.domain_id, robot.namespace)
    live = SimpleNamespace(robot=info, name=node.name, key=node.key, row=store.NodeRow(node.id, node.key, 0, True))
    return SimpleNamespace(
        config={"LOG_BUFFER": buffer},
        nodes={node.key: live},
        robot_for=lambda domain_id, name: info if domain_id == robot.domain_id else None,
        relay=FakeRelay(),
    )


def entry(robot: Robot, logger: str, i: int, level: int = 20) -> LogEntry:
    stamp = datetime(2026, 5, 1, 12, 0, 0, tzinfo=timezone.utc) + timedelta(microseconds=1001 * i)
    return LogEntry(robot.domain_id, stamp, level, logger, f"message {i}", "f.cpp" * 60, "fn", -1 if i == 0 else i)


def test_pipeline_pushes_the_stored_records_as_before(robot):
    robot_row, node = robot
    gateway = fake_gateway(robot_row, node)
    pipeline = LogPipeline(gateway)
    for i in range(6):
        pipeline.on_log(robot_row.domain_id, SimpleNamespace())  # malformed: ignored
        pipeline.buffer.append(entry(robot_row, "scanner" if i % 2 else "joystick", i, level=(20, 40, 45)[i % 3]))
    pipeline.buffer.append(LogEntry(999, dj_timezone.now(), 20, "elsewhere", "", "", "", 0))  # no robot: not stored
    async_to_sync(pipeline.flush)()

    assert pipeline.stored == 6 and len(pipeline.buffer) == 0
    by_group: dict[str, list[dict]] = {}
    for groups, message in gateway.relay.sent:
        assert message["type"] == "node.logs"
        for group in groups:
            by_group.setdefault(group, []).extend(message["records"])
    robot_records = by_group[protocol.robot_group(robot_row.id)]
    node_records = by_group[protocol.node_group(node.key)]
    assert len(robot_records) == 6 and [r["id"] for r in node_records] == [r["id"] for r in robot_records[1::2]]
    for payload in robot_records:
        record = LogRecord.objects.select_related("node").get(id=payload["id"])
        # What the push sent before: the saved model's as_dict() plus the node's key.
        assert payload == {**record.as_dict(), "node_id": record.node.key if record.node else None}
        assert list(payload) == ["id", "stamp", "level", "logger", "message", "file", "function", "line", "node_id"]
    assert {r["level"] for r in robot_records} == {"INFO", "ERROR"}  # 45 is no ROS level: stored as INFO
    assert LogRecord.objects.get(id=robot_records[0]["id"]).line == 0 and len(robot_records[0]["file"]) == 255
    assert [e.message for e in pipeline.recent_errors[node.key]] == ["message 1", "message 5"]  # levels 40, 45


def test_pipeline_keeps_the_bounded_buffer_and_its_drop_count(robot):
    robot_row, node = robot
    gateway = fake_gateway(robot_row, node, buffer=5)
    pipeline = LogPipeline(gateway)
    for i in range(12):
        pipeline.buffer.append(entry(robot_row, "scanner", i))
    assert (pipeline.buffer.received, pipeline.buffer.dropped, len(pipeline.buffer)) == (12, 7, 5)
    async_to_sync(pipeline.flush)()
    assert pipeline.stored == 5
    assert list(LogRecord.objects.order_by("id").values_list("message", flat=True)) == [
        f"message {i}" for i in range(7, 12)]


def test_a_naive_stamp_is_stored_as_the_orm_stores_it(robot):
    row = LogRow(robot[0].id, None, "a", datetime(2026, 7, 1, 12, 30), 20, "naive", "", "", 0)
    with pytest.warns(RuntimeWarning, match="naive datetime"):
        fast = raw(store.insert_logs([row]))
    with pytest.warns(RuntimeWarning, match="naive datetime"):
        orm = raw(store._insert_logs_orm([row]))
    assert fast[0][1:] == orm[0][1:]
