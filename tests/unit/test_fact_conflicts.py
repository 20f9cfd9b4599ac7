"""The request path and the ingest process apply a reply's facts side by side, in two
transactions of their own: on PostgreSQL (row locks; SQLite has one writer at a time) neither
may hold the other up, and a deadlock victim applies its facts again instead of failing the
request. Runs on PostgreSQL only (`make test-postgres`)."""
from __future__ import annotations

import threading
import time
from collections.abc import Callable

import pytest
from django.db import connection, transaction

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import Gateway, GroupRun, ManagedNode, Robot
from lifecycle_site.ingest.facts import apply_facts
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm
from tests.gateway_part import GatewayPart

GATEWAY = "cell-c"
HOLD_S = 5.0  # how long the other transaction stays open at most


@pytest.fixture
def cell(transactional_db) -> tuple[GatewayPart, Robot, ManagedNode]:
    assert connection.vendor == "postgresql", "this module runs under `make test-postgres`"
    robot = Robot.objects.create(name="conflict-agv", domain_id=41, gateway=Gateway.objects.create(name=GATEWAY))
    part = GatewayPart(GATEWAY)
    apply_facts(GATEWAY, [part.fact(protocol.NODE_SEEN, robot=robot.name, node="/lidar")])
    return part, robot, ManagedNode.objects.get(robot=robot, name="/lidar")


def reply_facts(part: GatewayPart, robot: Robot) -> list[dict]:
    """What a configure's reply carries: the node's new state, then the audit record."""
    return [part.fact(protocol.NODE_STATE, robot=robot.name, node="/lidar", state_id=sm.INACTIVE),
            part.transition(robot.name, "/lidar", sm.CONFIGURE, "configure", sm.UNCONFIGURED, sm.INACTIVE)]


def beside(work: Callable[[threading.Event], None]) -> tuple[threading.Thread, threading.Event]:
    """Run ``work`` in a thread of its own (its own database connection); it sets the event
    once it holds what it takes."""
    holding = threading.Event()

    def run() -> None:
        try:
            work(holding)
        finally:
            connection.close()

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    assert holding.wait(10), "the other transaction did not start"
    return thread, holding


def test_a_runs_progress_does_not_hold_up_an_audit_record_of_its_robot(cell):
    part, robot, _ = cell
    run = GroupRun.objects.create(id=protocol.new_id(), robot=robot, operation="restart")
    release = threading.Event()

    def ingest(holding: threading.Event) -> None:  # as the ingest applies a batch: in its own transaction
        with transaction.atomic():
            apply_facts(GATEWAY, [part.fact(protocol.RUN, run_id=run.id, robot=robot.name, status="running",
                                            message="", results=[])])
            holding.set()
            release.wait(HOLD_S)

    thread, _ = beside(ingest)
    started = time.monotonic()
    try:
        applied = apply_facts(GATEWAY, reply_facts(part, robot))
        took = time.monotonic() - started
    finally:
        release.set()
        thread.join(HOLD_S + 5)
    # Before: the record's foreign key check waited for the run's lock on the robot's row.
    assert took < 1.0, f"the reply's facts waited {took:.1f} s for the run's transaction"
    assert [r.transition_label for r in applied.created] == ["configure"]


def test_a_deadlock_victim_applies_its_facts_again(cell, caplog):
    part, robot, lidar = cell

    def rival(holding: threading.Event) -> None:
        """Takes the robot's row, waits until the reply's transaction waits for it (the record's
        foreign key check at commit), then wants the node's row that transaction updated."""
        with transaction.atomic(), connection.cursor() as cursor:
            cursor.execute("SET LOCAL deadlock_timeout = '10s'")  # the other side sees it first: the victim
            cursor.execute("SELECT id FROM fleet_robot WHERE id = %s FOR UPDATE", [robot.pk])
            holding.set()
            end = time.monotonic() + HOLD_S
            while time.monotonic() < end:
                cursor.execute("SELECT count(*) FROM pg_stat_activity WHERE wait_event_type = 'Lock' "
                               "AND pid <> pg_backend_pid()")
                if cursor.fetchone()[0]:
                    break
                time.sleep(0.02)
            cursor.execute("UPDATE fleet_managednode SET last_seen = now() WHERE id = %s", [lidar.pk])

    thread, _ = beside(rival)
    try:
        applied = apply_facts(GATEWAY, reply_facts(part, robot))
    finally:
        thread.join(HOLD_S + 15)
    assert [r.transition_label for r in applied.created] == ["configure"]
    assert TransitionRecord.objects.filter(robot=robot).count() == 1
    assert ManagedNode.objects.get(pk=lidar.pk).state_label == "inactive"
    assert "again after a database conflict (deadlock detected)" in caplog.text
