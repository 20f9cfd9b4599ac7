"""Log records written as plain tuples (log_store.insert_logs) read back through the ORM exactly as
if the ORM had written them, with the ids the live push sends; a gateway's log batch becomes
those rows and those pushes."""
from __future__ import annotations

from datetime import datetime, timedelta, timezone

import pytest
from django.db import IntegrityError, connection
from django.utils import timezone as dj_timezone

from lifecycle_site.fleet.models import Gateway, LogRecord, ManagedNode, Robot
from lifecycle_site.gateway_link.gateway_input import FactRejected
from lifecycle_site.ingest import log_store as store
from lifecycle_site.ingest.log_store import LogRow
from ros_gateway.shared import protocol

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


def record(robot: str, node: str, logger: str, i: int, level: int = 20) -> list:
    """One record of a logs-stream batch, as a gateway sends it."""
    stamp = datetime(2026, 5, 1, 12, 0, 0, tzinfo=timezone.utc) + timedelta(microseconds=1001 * i)
    return [robot, node, logger, stamp.isoformat(), level, f"message {i}", "f.cpp" * 60, "fn", -1 if i == 0 else i]


def test_a_batch_is_stored_for_the_gateways_robots_and_pushed_with_the_stored_ids(robot):
    robot_row, node = robot
    other = Robot.objects.create(name="elsewhere", domain_id=5, gateway=Gateway.objects.create(name="cell-z"))
    records = [record("store-agv", "/scanner" if i % 2 else "", "scanner" if i % 2 else "joystick", i,
                      level=(20, 40, 45)[i % 3]) for i in range(6)]
    records.append(record(other.name, "", "x", 99))  # another gateway's robot: not this batch's to store
    records.append(record("no-such-robot", "", "x", 98))
    pushes = store.store_batch(store.LogTargets(robot_row.gateway.name), {"records": records})

    assert LogRecord.objects.count() == 6
    by_group: dict[str, list[dict]] = {}
    for group, message in pushes:
        assert message["type"] == "node.logs" and len(message["records"]) <= store.PUSH_CHUNK
        by_group.setdefault(group, []).extend(message["records"])
    assert set(by_group) == {protocol.robot_group(robot_row.id), protocol.node_group(node.key)}
    robot_records = by_group[protocol.robot_group(robot_row.id)]
    node_records = by_group[protocol.node_group(node.key)]
    assert len(robot_records) == 6 and [r["id"] for r in node_records] == [r["id"] for r in robot_records[1::2]]
    for payload in robot_records:
        stored = LogRecord.objects.select_related("node").get(id=payload["id"])
        # What the push sent before: the saved model's as_dict() plus the node's key.
        assert payload == {**stored.as_dict(), "node_id": stored.node.key if stored.node else None}
        assert list(payload) == ["id", "stamp", "level", "logger", "message", "file", "function", "line", "node_id"]
    assert {r["level"] for r in robot_records} == {"INFO", "ERROR"}  # 45 is no ROS level: stored as INFO
    assert LogRecord.objects.get(id=robot_records[0]["id"]).line == 0 and len(robot_records[0]["file"]) == 255


def test_a_big_batch_is_pushed_in_bounded_chunks(robot):
    robot_row, _ = robot
    records = [record("store-agv", "", "talker", i) for i in range(450)]
    pushes = store.store_batch(store.LogTargets(robot_row.gateway.name), {"records": records})
    assert [len(m["records"]) for _, m in pushes] == [200, 200, 50]


@pytest.mark.parametrize("batch", [{"records": "no"}, {"records": [["too", "short"]]},
                                   {"records": [["store-agv", "", "a", "yesterday", 20, "m", "", "", 0]]}])
def test_a_malformed_batch_is_refused(robot, batch):
    with pytest.raises(FactRejected):
        store.store_batch(store.LogTargets(robot[0].gateway.name), batch)


def test_a_naive_stamp_is_stored_as_the_orm_stores_it(robot):
    row = LogRow(robot[0].id, None, "a", datetime(2026, 7, 1, 12, 30), 20, "naive", "", "", 0)
    with pytest.warns(RuntimeWarning, match="naive datetime"):
        fast = raw(store.insert_logs([row]))
    with pytest.warns(RuntimeWarning, match="naive datetime"):
        orm = raw(store._insert_logs_orm([row]))
    assert fast[0][1:] == orm[0][1:]
