"""The ingest process against a real Redis and the real SQLite test database, with the test
playing the gateways' part: what they XADD is stored once, in order, and what could not be
stored is counted where operators see it."""
from __future__ import annotations

import asyncio
import json
import signal
import time

import pytest
from asgiref.sync import sync_to_async
from channels.layers import get_channel_layer

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import Gateway, LogRecord, ManagedNode, Robot
from lifecycle_site.gateway_link import gateways, redis_users
from lifecycle_site.ingest import shares
from lifecycle_site.ingest.management.commands import ingest as ingest_command
from lifecycle_site.ingest.management.commands.ingest import Ingest
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm
from tests import stack
from tests.conftest import client_of
from tests.gateway_part import GatewayPart, clear_streams, forget_ingest_processes, iso


@pytest.fixture
def cell(transactional_db, redis_server, live_ingest_set_aside) -> tuple[GatewayPart, Robot]:
    forget_ingest_processes()
    clear_streams("cell-i")
    robot = Robot.objects.create(name="ingest-agv", domain_id=42, gateway=Gateway.objects.create(name="cell-i"))
    return GatewayPart("cell-i"), robot


def drain(ingest: Ingest, until, timeout: float = 10.0) -> None:
    """Turn the loop until ``until()`` holds."""
    stack.wait_for(lambda: ingest.step(block_ms=100) is not None and until(), timeout, "the ingest loop")


def test_facts_added_by_hand_are_stored_and_acknowledged(cell):
    part, robot = cell
    part.emit(part.fact(protocol.NODE_SEEN, robot=robot.name, node="/lidar"),
              part.fact(protocol.NODE_STATE, robot=robot.name, node="/lidar", state_id=sm.INACTIVE),
              part.transition(robot.name, "/lidar", sm.CONFIGURE, "configure", sm.UNCONFIGURED, sm.INACTIVE))
    ingest = Ingest()
    assert ingest.hold_lease()
    drain(ingest, lambda: TransitionRecord.objects.exists())
    lidar = ManagedNode.objects.get(robot=robot, name="/lidar")
    assert (lidar.alive, lidar.state_label) == (True, "inactive")
    stream = protocol.facts_stream(gateways.channel_prefix(), "cell-i")
    group = [g for g in part.redis.xinfo_groups(stream) if g["name"] == protocol.INGEST_GROUP.encode()][0]
    assert group["pending"] == 0
    row = Gateway.objects.get(name="cell-i")
    assert (row.facts_seq, row.facts_lost, row.facts_rejected) == (3, 0, 0)
    assert row.facts_cursor == group["last-delivered-id"].decode()


def test_facts_a_reply_carried_settle_longer_than_others(cell, monkeypatch):
    """Facts a reply carries are applied by the request first: ingest waits SETTLE_S for them.
    Others (a node's own transitions, discovery) wait only SETTLE_OTHERS_S; old ones not at all."""
    ingest = Ingest()
    ingest.refresh()
    stream = protocol.facts_stream(gateways.channel_prefix(), "cell-i").encode()
    slept: list[float] = []
    now_ms = 1_795_000_000_000
    monkeypatch.setattr(ingest_command.time, "time", lambda: now_ms / 1000)  # the clock stands still
    monkeypatch.setattr(ingest_command.time, "sleep", slept.append)
    just_now, a_while_ago = f"{now_ms}-0".encode(), f"{now_ms - 1000}-0".encode()
    replied = {b"f": b"{}", protocol.REPLIED.encode(): b"1"}
    ingest.settle([(stream, [(a_while_ago, replied), (a_while_ago, {b"f": b"{}"})])])
    assert slept == []
    ingest.settle([(stream, [(just_now, {b"f": b"{}"})])])
    assert slept == [pytest.approx(ingest_command.SETTLE_OTHERS_S)]
    ingest.settle([(stream, [(just_now, {b"f": b"{}"}), (just_now, replied)])])
    assert slept[1:] == [pytest.approx(ingest_command.SETTLE_S)]


def test_a_second_ingest_process_stands_by(cell):
    first, second = Ingest(), Ingest()
    assert first.hold_lease() and not second.hold_lease()
    assert first.hold_lease()  # renewed
    first.release_lease()
    assert second.hold_lease()
    second.release_lease()


def test_audit_records_and_log_lines_reach_the_pages_with_their_ids(cell):
    part, robot = cell
    part.emit(part.fact(protocol.NODE_SEEN, robot=robot.name, node="/lidar"))
    ingest = Ingest()
    ingest.hold_lease()
    drain(ingest, lambda: ManagedNode.objects.filter(robot=robot).exists())
    key = "ingest-agv.lidar"
    layer = get_channel_layer()

    async def scenario() -> list[dict]:
        channel = await layer.new_channel()
        await layer.group_add(protocol.node_group(key), channel)
        part.emit(part.transition(robot.name, "/lidar", sm.CONFIGURE, "configure", 1, 2))
        stamp = iso()
        part.log_batch([[robot.name, "/lidar", "lidar", stamp, 40, "no scan", "l.cpp", "scan", 7],
                        [robot.name, "", "launch", stamp, 20, "not a node's", "", "", 0]], dropped=3)
        await sync_to_async(drain, thread_sensitive=False)(ingest, lambda: LogRecord.objects.count() == 2)
        return [await asyncio.wait_for(layer.receive(channel), 5) for _ in range(2)]

    received = sorted(asyncio.run(scenario()), key=lambda m: m["type"])
    record = TransitionRecord.objects.get()
    assert received[0] == {"type": "audit.record", "record": record.as_dict()}
    stored = LogRecord.objects.get(node__key=key)
    assert received[1]["type"] == "node.logs"
    assert received[1]["records"] == [{**stored.as_dict(), "node_id": key}]
    counted = Gateway.objects.get(name="cell-i")
    assert (counted.logs_dropped, counted.logs_received) == (3, 2)  # /metrics reports both


def test_entries_applied_but_not_acknowledged_are_not_applied_again(cell, monkeypatch):
    part, robot = cell
    stamp = iso()
    part.log_batch([[robot.name, "", "launch", stamp, 20, f"line {i}", "", "", 0] for i in range(5)])
    part.emit(part.transition(robot.name, "/lidar", sm.CONFIGURE, "configure", 1, 2))
    crashing = Ingest()
    crashing.hold_lease()
    crashing.refresh()
    monkeypatch.setattr(crashing.redis, "xack", lambda *a: (_ for _ in ()).throw(SystemExit("killed")))
    with pytest.raises(SystemExit):  # committed, then gone before the acknowledgement
        for _ in range(10):
            crashing.step(block_ms=100)
    crashing.release_lease()
    monkeypatch.undo()
    stored = (LogRecord.objects.count(), TransitionRecord.objects.count())
    assert stored in ((5, 0), (0, 1), (5, 1))

    successor = Ingest()
    successor.hold_lease()
    drain(successor, lambda: (LogRecord.objects.count(), TransitionRecord.objects.count()) == (5, 1))
    for _ in range(3):
        successor.step(block_ms=50)
    assert (LogRecord.objects.count(), TransitionRecord.objects.count()) == (5, 1)
    for stream in (protocol.facts_stream(part.prefix, "cell-i"), protocol.logs_stream(part.prefix, "cell-i")):
        assert part.redis.xpending(stream, protocol.INGEST_GROUP)["pending"] == 0


def test_trimmed_facts_are_counted_as_lost_and_shown(cell):
    part, robot = cell
    part.emit(*[part.fact(protocol.NODE_SEEN, robot=robot.name, node=f"/n{i}") for i in range(3)])
    ingest = Ingest()
    ingest.hold_lease()
    drain(ingest, lambda: Gateway.objects.get(name="cell-i").facts_seq == 3)
    part.emit(*[part.fact(protocol.NODE_SEEN, robot=robot.name, node=f"/n{i}") for i in range(3, 10)])
    part.redis.xtrim(protocol.facts_stream(part.prefix, "cell-i"), maxlen=3, approximate=False)  # 4-7 gone
    drain(ingest, lambda: Gateway.objects.get(name="cell-i").facts_seq == 10)
    row = Gateway.objects.get(name="cell-i")
    assert row.facts_lost == 4
    assert sorted(robot.nodes.values_list("name", flat=True)) == ["/n0", "/n1", "/n2", "/n7", "/n8", "/n9"]

    client = client_of("lost-viewer", "viewer")
    listed = {g["name"]: g for g in client.get("/api/v1/gateways").json()["gateways"]}
    assert listed["cell-i"]["facts_lost"] == 4 and listed["cell-i"]["robots"] == ["ingest-agv"]
    page = client.get("/").content.decode()
    assert "4 facts lost" in page


def test_heartbeats_configs_and_redis_users_are_kept(cell):
    part, robot = cell
    part.beat(version="1.2.3", nodes=7, domains=[42], dds={"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"},
              outbox={"facts": 0, "log_batches": 0, "facts_dropped": 5, "logs_dropped": 0})
    ManagedNode.objects.create(robot=robot, name="/lidar", order=1, desired_state="active")
    row = Gateway.objects.get(name="cell-i")
    row.redis_password_sha256 = redis_users.password_sha256("s3cret-for-the-test")
    row.save()
    part.redis.execute_command("ACL", "DELUSER", "gw-cell-i")
    part.emit(*[part.fact(protocol.NODE_SEEN, robot=robot.name, node="/camera") for _ in range(2)])
    ingest = Ingest()
    ingest.hold_lease()
    ingest.step(block_ms=100)
    row.refresh_from_db()
    assert (row.version, row.node_count, row.domains, row.outbox["facts_dropped"]) == ("1.2.3", 7, [42], 5)
    assert row.last_beat is not None and row.dds == {"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}
    config = json.loads(part.redis.get(protocol.config_key(part.prefix, "cell-i")))
    assert config["gateway"] == "cell-i" and config["version"]
    assert config["robots"][0]["name"] == "ingest-agv"
    assert config["robots"][0]["nodes"]["/lidar"] == {"order": 1, "desired_state": "active", "keep": "off"}
    assert redis_users.user_is_current(row, part.redis)
    part.redis.execute_command("ACL", "DELUSER", "gw-cell-i")


def test_the_backlog_counts_what_is_not_stored_yet(cell):
    part, robot = cell
    ingest = Ingest()
    ingest.hold_lease()
    ingest.refresh()
    part.emit(*[part.fact(protocol.NODE_SEEN, robot=robot.name, node=f"/n{i}") for i in range(25)])
    ingest.copy_beats()
    assert Gateway.objects.get(name="cell-i").backlog == 25
    drain(ingest, lambda: Gateway.objects.get(name="cell-i").facts_seq == 25)
    ingest.copy_beats()
    assert Gateway.objects.get(name="cell-i").backlog == 0


def test_the_ingest_process_catches_up_in_order_after_a_stop(cell):
    part, robot = cell
    process = stack.start_ingest("ingest-catch-up")
    try:
        part.emit(part.fact(protocol.NODE_SEEN, robot=robot.name, node="/lidar"))
        stack.wait_for(lambda: ManagedNode.objects.filter(robot=robot).exists() or not process.alive(), 20,
                       "the ingest process to store a fact")
        assert process.stop(signal.SIGTERM) == 0, process.output()
        assert "ingest stopped after storing 1 entries" in process.output()

        states = [sm.UNCONFIGURED, sm.CONFIGURING, sm.INACTIVE, sm.ACTIVATING, sm.ACTIVE]
        facts = []
        for i in range(1000):  # while nothing reads them
            facts.append(part.fact(protocol.NODE_STATE, robot=robot.name, node=f"/n{i % 10}",
                                   state_id=states[(i // 10) % len(states)]))
        facts.append(part.transition(robot.name, "/lidar", sm.CONFIGURE, "configure", 1, 2))
        part.emit(*facts)
        started = time.monotonic()
        process = stack.start_ingest("ingest-catch-up")
        stack.wait_for(lambda: TransitionRecord.objects.exists() or not process.alive(), 60,
                       "the ingest process to catch up")
        took = time.monotonic() - started
        final = dict(ManagedNode.objects.filter(robot=robot).exclude(name="/lidar").values_list("name", "state_id"))
        assert final == {f"/n{i}": states[(99 // 10) % len(states)] for i in range(10)}  # the last of each, in order
        row = Gateway.objects.get(name="cell-i")
        assert (row.facts_seq, row.facts_lost, row.facts_rejected) == (1002, 0, 0)
        assert took < 30, f"catching up on 1,000 facts took {took:.1f} s"
        # What is stored leaves Redis (trimmed by whole blocks of entries, so a few may stay).
        stack.wait_for(lambda: part.redis.xlen(protocol.facts_stream(part.prefix, "cell-i")) < 200, 10,
                       "the stored facts trimmed from the stream")
    finally:
        process.stop()


def test_runs_of_a_gateway_silent_past_the_bound_end_failed_and_others_stay(cell, settings):
    from lifecycle_site.fleet.models import GroupRun
    from lifecycle_site.ingest.run_orphans import fail_runs_of_silent_gateways

    _part, robot = cell
    other = Robot.objects.create(name="ingest-arm", domain_id=43, gateway=Gateway.objects.create(name="cell-j"))
    runs = {r.robot.name: r for r in (
        GroupRun.objects.create(id="run-of-cell-i", robot=robot, operation="bringup", status="running"),
        GroupRun.objects.create(id="run-of-cell-j", robot=other, operation="bringup", status="running"))}
    settings.LIFECYCLE = {**settings.LIFECYCLE, "RUN_ORPHAN_AFTER": 60.0}
    stack.write_beat("cell-i", at=time.time() - 30)  # silent, but not for long enough
    stack.write_beat("cell-j", at=time.time())
    fail_runs_of_silent_gateways()
    assert set(GroupRun.objects.values_list("status", flat=True)) == {"running"}
    stack.write_beat("cell-i", at=time.time() - 61)
    fail_runs_of_silent_gateways()
    failed = GroupRun.objects.get(id=runs["ingest-agv"].id)
    assert failed.status == "failed" and failed.finished is not None
    assert failed.message.startswith("the gateway cell-i has been silent since ") and "on record" in failed.message
    assert GroupRun.objects.get(id=runs["ingest-arm"].id).status == "running"
    # The verdict is where the gateway reads it (its own keys), should it come back.
    client, prefix = stack.redis_client(), gateways.channel_prefix()
    said = json.loads(client.get(protocol.verdict_key(prefix, "cell-i", failed.id)))
    assert (said["status"], said["message"]) == ("failed", failed.message)
    assert 0 < client.ttl(protocol.verdict_key(prefix, "cell-i", failed.id)) <= protocol.VERDICT_TTL_S
    assert not client.exists(protocol.verdict_key(prefix, "cell-j", runs["ingest-arm"].id))


def test_two_ingest_processes_share_the_gateways_and_apply_nothing_twice(cell):
    """Two ingest processes side by side: each reads the streams of its share of the gateways
    (one process per gateway at a time, so each gateway's facts are applied in order), and when
    one is killed the other takes its gateways over."""
    part, robot = cell
    parts = [part]
    for i in range(1, 4):
        name = f"cell-i{i}"
        clear_streams(name)
        Robot.objects.create(name=f"ingest-agv-{i}", domain_id=42, gateway=Gateway.objects.create(name=name))
        parts.append(GatewayPart(name))
    robots = {p.name: Robot.objects.get(gateway__name=p.name) for p in parts}
    states = [sm.UNCONFIGURED, sm.CONFIGURING, sm.INACTIVE, sm.ACTIVATING, sm.ACTIVE]

    def emit(count: int) -> None:
        for p in parts:
            name = robots[p.name].name
            facts = [p.fact(protocol.NODE_STATE, robot=name, node=f"/n{i % 4}", state_id=states[(i // 4) % 5])
                     for i in range(count)]
            facts += [p.transition(name, "/n0", sm.CONFIGURE, "configure", 1, 2, source="external")]
            p.emit(*facts)

    first, second = stack.start_ingest("ingest-share-1"), stack.start_ingest("ingest-share-2")
    try:
        emit(200)
        stack.wait_for(lambda: all(Gateway.objects.get(name=p.name).facts_seq == p.seq for p in parts), 60,
                       "every gateway's facts stored")

        def shared() -> bool:
            """Both hold some of these gateways, and each gateway is held by one of them."""
            held = [set(t.get("gateways") or []) & set(robots)
                    for t in shares.turns(part.redis, part.prefix) if t["pid"] in (first.pid, second.pid)]
            return len(held) == 2 and all(held) and not held[0] & held[1] and held[0] | held[1] == set(robots)

        stack.wait_for(shared, 30, "the two processes sharing the four gateways")
        print("DEBUG", shares.turns(part.redis, part.prefix), first.pid, second.pid)
        transitions = TransitionRecord.objects.filter(robot_name__startswith="ingest-agv").exclude(outcome="observed")
        assert transitions.count() == 4  # (the states no record explains are the chain's: observed)
        for p in parts:
            row = Gateway.objects.get(name=p.name)
            assert (row.facts_lost, row.facts_rejected) == (0, 0)
            final = dict(ManagedNode.objects.filter(robot=robots[p.name]).values_list("name", "state_id"))
            assert final == {f"/n{i}": states[(199 // 4) % 5] for i in range(4)}  # the last of each, in order

        first.kill()  # its gateways' leases run out; the other one takes them over
        emit(40)
        stack.wait_for(lambda: all(Gateway.objects.get(name=p.name).facts_seq == p.seq for p in parts), 60,
                       "the facts of every gateway stored after one process was killed")
        assert transitions.count() == 8
        assert all(Gateway.objects.get(name=p.name).facts_lost == 0 for p in parts)
    finally:
        first.stop()
        second.stop()


def test_catching_up_the_ingest_holds_the_database_only_briefly(cell):
    """F9: the ingest's write transactions are short (at most FACTS_PER_TRANSACTION facts or
    LOG_RECORDS_PER_TRANSACTION log records), so a write of the site waits a fraction of a
    second for it even while it stores a backlog of 100,000 log records (SQLite: one writer)."""
    part, robot = cell
    stamp = iso()
    for batch in range(500):
        part.log_batch([[robot.name, "", "launch", stamp, 20, f"line {batch}-{i}", "", "", 0] for i in range(200)])
    process = stack.start_ingest("ingest-brief")
    waits = []
    try:
        stack.wait_for(lambda: LogRecord.objects.exists() or not process.alive(), 30, "the ingest storing logs")
        while LogRecord.objects.count() < 100_000 and process.alive() and len(waits) < 2000:
            began = time.monotonic()
            Gateway.objects.filter(name="cell-i").update(description=f"written at {began}")  # a write of the site
            waits.append(time.monotonic() - began)
            time.sleep(0.02)
        assert LogRecord.objects.count() == 100_000, process.output()[-2000:]
    finally:
        process.stop()
    assert len(waits) > 10 and max(waits) < 1.0, f"the site's writes waited up to {max(waits):.2f} s"


def test_readyz_says_when_the_ingest_process_is_frozen(cell, client):
    """F9: an ingest process stopped (SIGSTOP) stores nothing; /readyz says so within its
    bound (the lease it held would have said "running" for 15 s, then "not running")."""
    forget_ingest_processes()
    process = stack.start_ingest("ingest-frozen")
    try:
        stack.wait_for(lambda: client.get("/readyz").json()["ingest"] == "running" or not process.alive(), 20,
                       "the ingest process reported as running")
        with stack.frozen(process.pid):
            frozen_at = time.monotonic()
            ready = stack.wait_for(lambda: (r := client.get("/readyz").json())["ingest"] == "stalled" and r, 20,
                                   "/readyz to call the ingest stalled")
            assert time.monotonic() - frozen_at < 15
            assert ready["status"] == "degraded" and "no ingest process has finished a turn" in ready["ingest_problem"]
        stack.wait_for(lambda: client.get("/readyz").json()["ingest"] == "running", 20, "running again")
    finally:
        process.stop()


def test_entries_no_fact_can_be_made_of_are_refused_and_the_ingest_goes_on(cell):
    """Review of issue 25: JSON nested deeper than Python's stack, a robot given as a list, a
    sequence number beyond any integer column, an instance id of 100 characters. Each was an
    exception that stopped the ingest process, for every gateway, again after each restart."""
    part, robot = cell
    stream = protocol.facts_stream(part.prefix, "cell-i")
    part.redis.xadd(stream, {"f": "[" * 100_000 + "]" * 100_000})
    part.redis.xadd(stream, {"f": protocol.encode(part.fact(protocol.NODE_STATE, robot=[robot.name], node="/a",
                                                            state_id=1))})
    huge = part.fact(protocol.NODE_SEEN, robot=robot.name, node="/b")
    huge.update(seq=2**64, instance="x" * 100)
    part.redis.xadd(stream, {"f": protocol.encode(huge)})
    good = part.fact(protocol.NODE_SEEN, robot=robot.name, node="/good")
    part.emit(good)
    ingest = Ingest()
    drain(ingest, lambda: ManagedNode.objects.filter(robot=robot, name="/good").exists())
    row = Gateway.objects.get(name="cell-i")
    assert row.facts_rejected == 2 and row.quarantined is None
    assert sorted(robot.nodes.values_list("name", flat=True)) == ["/b", "/good"]  # the numbers left aside


def test_entries_trimmed_while_waiting_to_be_acknowledged_do_not_cut_the_gateway_off(cell, monkeypatch):
    """Review of issue 25: delivered to an ingest process that died before its acknowledgement,
    then trimmed by the gateway's MAXLEN: read again, they come back without fields."""
    part, robot = cell
    part.emit(*[part.fact(protocol.NODE_SEEN, robot=robot.name, node=f"/n{i}") for i in range(5)])
    crashing = Ingest()
    crashing.refresh()
    monkeypatch.setattr(crashing, "apply", lambda *a: (_ for _ in ()).throw(SystemExit("killed")))
    with pytest.raises(SystemExit):  # the entries delivered, then gone before it applied them
        for _ in range(10):
            crashing.step(block_ms=100)
    crashing.release_lease()
    part.redis.xtrim(protocol.facts_stream(part.prefix, "cell-i"), maxlen=0, approximate=False)
    part.emit(part.fact(protocol.NODE_SEEN, robot=robot.name, node="/after"))
    successor = Ingest()
    drain(successor, lambda: ManagedNode.objects.filter(robot=robot, name="/after").exists())
    row = Gateway.objects.get(name="cell-i")
    assert row.quarantined is None and row.facts_lost == 5
