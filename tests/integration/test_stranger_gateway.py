"""A gateway is a stranger (issue 25): with nothing but the credentials ``manage.py add_gateway``
gives a cell, an attacker tries what the probe of 2026-11-24 did (F1-F5). The real stack: the
session's Redis with the real ACL users, the real ingest process (its live relay and Redis
guard), a real cell gateway with real demo nodes beside the attacker. Each attack must fail or
cut off only the attacker, and the honest cell must go on as before."""
from __future__ import annotations

import asyncio
import json
import threading
import time
from pathlib import Path

import pytest
import redis
from channels.layers import get_channel_layer
from django.core.management import call_command
from django.test import Client

from lifecycle_site.alerts.models import Alert, Rule
from lifecycle_site.api.models import ApiToken
from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import Gateway, ManagedNode, Robot
from lifecycle_site.gateway_link import gateways
from lifecycle_site.ingest import shares
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm
from tests import stack
from tests.conftest import client_of, make_user
from tests.gateway_part import iso
from tests.integration.conftest import register, transition, wait_node

GOOD, ROBOT, NAMESPACE, OFFSET = "cell-good", "sg-agv", "/sg", 30


def credentials(name: str, tmp: Path) -> dict[str, str]:
    path = tmp / f"{name}.env"
    call_command("add_gateway", name, env_file=str(path))
    return dict(line.split("=", 1) for line in path.read_text().splitlines() if "=" in line)


@pytest.fixture(scope="module")
def cell(redis_server, live_db, ingest, tmp_path_factory):
    """The honest cell: its gateway with its own Redis user, two demo nodes."""
    tmp = tmp_path_factory.mktemp("stranger")
    register(ROBOT, stack.domain(OFFSET), namespace=NAMESPACE, gateway=GOOD)
    gateway = stack.start_gateway(GOOD, **credentials(GOOD, tmp))
    robot = stack.start_robot("sg-nodes", stack.domain(OFFSET), "lidar_driver,camera_driver", namespace=NAMESPACE)
    try:
        for node in ("lidar_driver", "camera_driver"):
            wait_node(None, f"{ROBOT}.sg.{node}", alive=True, timeout=30)
        yield tmp
    finally:
        robot.stop()
        gateway.stop()
        Robot.objects.filter(gateway__name__in=[GOOD, *Gateway.objects.filter(name__startswith="evil-")
                                                .values_list("name", flat=True)]).delete()
        Gateway.objects.filter(name__startswith="evil-").delete()


@pytest.fixture
def api(live_db) -> Client:
    client = client_of("sg-operator", "operator")
    return client


def attacker(name: str, tmp: Path) -> redis.Redis:
    """A registered gateway with a robot of its own, and a Redis client with its credentials."""
    register(f"{name}-agv", stack.domain(OFFSET), namespace=f"/{name.replace('-', '_')}", gateway=name)
    url = credentials(name, tmp)["REDIS_URL"]
    client = redis.Redis.from_url(url, socket_timeout=30)
    client.url = url  # type: ignore[attr-defined]
    lease = shares.gateway_lease_key(gateways.channel_prefix(), name)
    stack.wait_for(lambda: stack.redis_client().exists(lease), 15, f"an ingest process reading {name}'s streams")
    return client


def metrics() -> str:
    _, token = ApiToken.issue(make_user("sg-prometheus", "viewer"), "scrape")
    answer = Client().get("/metrics", HTTP_AUTHORIZATION=f"Bearer {token}")
    assert answer.status_code == 200
    return answer.content.decode()


def status(api: Client, name: str) -> dict:
    return {g["name"]: g for g in api.get("/api/v1/gateways").json()["gateways"]}[name]


def toggled(api: Client, key: str) -> int:
    """One transition of an honest node (configure, or cleanup back): the status code."""
    node = ManagedNode.objects.get(key=key)
    return transition(api, key, "cleanup" if node.state_label == "inactive" else "configure").status_code


def test_f1_no_script_no_database_switch_redis_answers_everyone(cell, api):
    evil = attacker("evil-f1", cell)
    began = time.monotonic()
    for attempt in (lambda: evil.eval("local i=0 while i<1300000000 do i=i+1 end return i", 0),
                    lambda: evil.eval("while true do end", 0),
                    lambda: evil.execute_command("SELECT", 1)):
        with pytest.raises(redis.exceptions.NoPermissionError):
            attempt()
    assert time.monotonic() - began < 1.0
    assert toggled(api, f"{ROBOT}.sg.lidar_driver") == 200
    assert Client().get("/readyz").status_code == 200


def test_f2_a_broken_stream_quarantines_its_gateway_and_the_others_go_on(cell, api):
    evil = attacker("evil-f2", cell)
    rule = Rule.objects.create(name="evil-f2 cut off", kind=Rule.Kind.GATEWAY_OFFLINE,
                               gateway=Gateway.objects.get(name="evil-f2"))
    prefix = gateways.channel_prefix()
    stack.wait_for(lambda: evil.delete(protocol.facts_stream(prefix, "evil-f2")) or True, 5, "a first delete")
    evil.set(protocol.facts_stream(prefix, "evil-f2"), "x")  # its own key, of the wrong type
    stack.wait_for(lambda: status(api, "evil-f2")["status"] == "quarantined", 15, "evil-f2 quarantined")
    seen = status(api, "evil-f2")
    assert "facts stream" in seen["reason"] and "string" in seen["reason"], seen
    with pytest.raises(redis.exceptions.ConnectionError):  # cut off: its connection closed ...
        evil.ping()
    with pytest.raises(redis.exceptions.AuthenticationError):  # ... and it cannot log in again
        redis.Redis.from_url(evil.url).ping()
    # The honest cell's facts are still stored: a transition's record, and one made by hand at once.
    before = TransitionRecord.objects.filter(robot_name=ROBOT).count()
    assert toggled(api, f"{ROBOT}.sg.camera_driver") == 200
    stack.wait_for(lambda: stack.facts_read(GOOD), 10, "the good cell's facts read")
    assert TransitionRecord.objects.filter(robot_name=ROBOT).count() == before + 1
    # Metrics and readiness say so.
    assert 'lifecycle_gateway_quarantined{gateway="evil-f2"} 1.0' in metrics()
    ready = Client().get("/readyz").json()
    assert ready["gateways"]["quarantined"] >= 1, ready
    # The fleet page names it and why; an alert fires.
    page = api.get("/").content.decode()
    assert "quarantined" in page and "evil-f2" in page
    alert = stack.wait_for(lambda: Alert.objects.filter(rule=rule).first(), 15, "the rule's alert")
    assert "Gateway evil-f2 is quarantined" in alert.summary, alert.summary
    rule.delete()


def test_f3_a_gateway_filling_redis_is_cut_off_and_commands_for_others_go_on(cell, api):
    evil = attacker("evil-f3", cell)
    prefix = gateways.channel_prefix()
    site = stack.redis_client()
    limit = int(site.config_get("maxmemory")["maxmemory"])
    assert limit, "the test Redis has a maxmemory (noeviction), as every deployment's has"
    chunk = "x" * (1024 * 1024)
    written, answers, stop = [0], [], threading.Event()

    def fill() -> None:
        try:
            for i in range(2 * limit // len(chunk)):
                with evil.pipeline(transaction=False) as pipe:
                    for j in range(8):
                        pipe.lpush(protocol.reply_key(prefix, "evil-f3", f"r{i}-{j}"), chunk)
                    pipe.execute()
                written[0] += 8 * len(chunk)
        except redis.RedisError:
            pass  # cut off (or Redis full for it): what a stranger gets
        finally:
            stop.set()

    def command() -> None:  # an operator of the honest cell, all along
        while not stop.is_set():
            answers.append(toggled(api, f"{ROBOT}.sg.lidar_driver"))

    filler, operator = threading.Thread(target=fill), threading.Thread(target=command)
    filler.start()
    operator.start()
    filler.join(120)
    operator.join(60)
    assert stop.is_set()
    seen = stack.wait_for(lambda: (found := status(api, "evil-f3"))["status"] == "quarantined" and found, 10,
                          f"evil-f3 cut off (it wrote {written[0] / 1e6:.0f} MB of Redis's {limit / 1e6:.0f} MB)")
    assert "Redis keys held" in seen["reason"], seen
    assert int(site.info("memory")["used_memory"]) < limit // 2  # its keys are gone
    answers.append(toggled(api, f"{ROBOT}.sg.lidar_driver"))
    assert set(answers) == {200}, answers


def test_f3_redis_filled_before_the_guard_counts_the_site_relieves_it_and_answers(cell, api, ingest):
    """As on an Industrial Edge device, Redis's maxmemory only 40 MB above what it holds, and the
    guard late (the ingest processes, where it counts, frozen): the gateway fills Redis. The
    site's next command finds Redis full, has the gateway's keys counted at once (cutting it off)
    and is sent again: answered, not refused."""
    evil = attacker("evil-f3s", cell)
    prefix = gateways.channel_prefix()
    site = stack.redis_client()
    before = site.config_get("maxmemory")["maxmemory"]
    site.config_set("maxmemory", int(site.info("memory")["used_memory"]) + 40 * 1024 * 1024)
    try:
        config = protocol.config_key(prefix, "evil-f3s")
        stack.wait_for(lambda: json.loads(site.get(config) or "{}").get("limits", {}).get("redis_bytes", 1e12)
                       <= 6 * 1024 * 1024, 30, "the gateways' quota following Redis's maxmemory")
        with stack.frozen(ingest.current.pid):
            size, written, refused = 1024 * 1024, 0, 0
            while size >= 16:  # to the brim: each size until Redis refuses it, then half of it
                try:
                    evil.lpush(protocol.reply_key(prefix, "evil-f3s", f"r{written}"), "x" * size)
                    written += 1
                except redis.exceptions.OutOfMemoryError:
                    refused += 1
                    size //= 2
            assert written > 30 and refused  # Redis was full, for the gateway and for everyone
            gateways.forget()
            node = ManagedNode.objects.get(key=f"{ROBOT}.sg.camera_driver")
            answer = transition(api, node.key, "cleanup" if node.state_label == "inactive" else "configure")
            assert answer.status_code == 200, answer.json()
            seen = status(api, "evil-f3s")
            assert seen["status"] == "quarantined" and "Redis keys held" in seen["reason"], seen
            assert int(site.info("memory")["used_memory"]) < int(site.config_get("maxmemory")["maxmemory"]) // 2
    finally:
        site.config_set("maxmemory", before)


def test_f4_live_updates_reach_pages_only_as_the_site_checked_them(cell, api):
    evil = attacker("evil-f4", cell)
    prefix = gateways.channel_prefix()
    evil_robot = Robot.objects.get(name="evil-f4-agv")
    good = ManagedNode.objects.select_related("robot").get(key=f"{ROBOT}.sg.lidar_driver")
    layer = get_channel_layer()

    def state(robot: str, name: str, state_id: int, **extra) -> dict:
        return {"type": "node.state", "node": {**protocol.node_payload(
            key=protocol.node_key(robot, name), robot=robot, name=name, state_id=state_id, alive=True,
            last_seen=iso()), **extra}}

    hostile = state(evil_robot.name, "/lidar", sm.ACTIVE)
    hostile["node"]["transitions"] = [{"id": 7, "label": '", "transition": "shutdown'}]
    attempts = [
        state(ROBOT, good.name, sm.FINALIZED),  # another cell's node
        state(f"{ROBOT} ", good.name, sm.FINALIZED), state(ROBOT.upper(), good.name, sm.FINALIZED),
        {"type": "node.state"},  # without a node: closed every open socket before
        {"type": "audit.record", "record": {"robot": ROBOT, "transition": "shutdown", "requested_by": "admin"}},
        {"type": "node.logs", "records": [{"level": "FATAL", "message": "reactor breach"}]},
        {"type": "run.progress", "run": {"id": "ab", "robot": ROBOT, "operation": "shutdown", "policy": "stop",
                                         "status": "running", "results": []}},
        hostile,
    ]

    async def scenario() -> list[dict]:
        channel = await layer.new_channel()
        for group in (protocol.FLEET_GROUP, protocol.robot_group(good.robot_id), protocol.node_group(good.key),
                      protocol.node_group(f"{evil_robot.name}.lidar"), "audit"):
            await layer.group_add(group, channel)
        for message in attempts:
            evil.xadd(protocol.live_stream(prefix, "evil-f4"), {"m": json.dumps(message)})
        received = []
        try:
            while True:
                received.append(await asyncio.wait_for(layer.receive(channel), 3))
        except asyncio.TimeoutError:
            return received

    received = asyncio.run(scenario())
    # The honest cell's own /rosout lines, stored by the site (each with its row id) and pushed to the
    # same groups, may arrive in the window too (its node's transitions in the tests before): not the
    # attacker's, whose node.logs the relay refused.
    stored = [m for m in received if m["type"] == "node.logs" and all(
        isinstance(r.get("id"), int) and "reactor breach" not in r.get("message", "") for r in m["records"])]
    received = [m for m in received if m not in stored]
    # Only the update about its own robot's node went out, rebuilt: its transitions from the state machine.
    about = [(m["type"], m.get("node", {}).get("robot") if isinstance(m.get("node"), dict) else m.get("node"))
             for m in received]
    assert set(about) <= {("node.state", evil_robot.name)}, about
    assert received and received[0]["node"]["transitions"] == [t.as_dict() for t in sm.valid_transitions(sm.ACTIVE)]
    stack.wait_for(lambda: Gateway.objects.get(name="evil-f4").live_refused >= 7, 10, "the refusals counted")
    assert status(api, "evil-f4")["status"] != "quarantined"  # refusing its content is enough
    # The honest cell's own updates still reach the pages, through the same relay.
    assert toggled(api, good.key) == 200


def test_f5_facts_about_what_it_does_not_own_are_refused_and_counted(cell, api):
    evil = attacker("evil-f5", cell)
    prefix = gateways.channel_prefix()
    admin = make_user("sg-admin", "admin")
    before = TransitionRecord.objects.count()
    instance = protocol.new_id()
    facts = []
    for seq, robot in enumerate([ROBOT, f"{ROBOT} ", ROBOT.upper(), ROBOT.replace("a", "\u0430"), f"{ROBOT}\u200b",
                                 "agv-3", '=HYPERLINK("http://x")', "evil-f5-agv"], start=1):
        now = iso()
        facts.append({"id": protocol.new_id(), "type": protocol.TRANSITION, "gateway": "evil-f5", "instance": instance,
                      "seq": seq, "at": now, "robot": robot, "node": "/lidar", "transition_id": sm.ACTIVE_SHUTDOWN,
                      "transition_label": "shutdown", "start_state": sm.ACTIVE, "result_state": sm.FINALIZED,
                      "outcome": "succeeded", "source": "dashboard", "user_id": admin.pk, "requested_at": now,
                      "completed_at": now, "error": "x" * 100_000, "run_id": ""})
    for fact in facts:
        evil.xadd(protocol.facts_stream(prefix, "evil-f5"), {"f": json.dumps(fact)})
    stack.wait_for(lambda: Gateway.objects.get(name="evil-f5").facts_rejected >= len(facts) - 1, 15,
                   "the facts about other robots refused and counted")
    # The one about its own robot is kept (a change of its own robot is on record whatever it
    # claims), but not on the admin's name nor as the dashboard's, and bounded.
    stack.wait_for(lambda: TransitionRecord.objects.count() == before + 1, 10, "its own robot's record")
    record = TransitionRecord.objects.order_by("-id").first()
    assert (record.robot_name, record.source, record.requested_by_name) == ("evil-f5-agv", "external", "")
    assert record.error.endswith(f"(the gateway said source dashboard, user #{admin.pk}; the site sent it no such "
                                 "request)") and len(record.error) < 4200
    assert status(api, "evil-f5")["facts_rejected"] == len(facts) - 1
