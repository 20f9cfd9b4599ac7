"""Faults injected into the real stack while users keep asking: a gateway frozen and continued,
a gateway killed in the middle of a transition, a robot process killed in the middle of one,
Redis frozen and Redis stopped, the ingest process stopped. Every request answers within its
bound and says plainly whether it was carried out; everything recovers without restarting the
site; and the audit log has exactly one record for each request made (counted here).

Killed gateways in the middle of a group run: test_killed_gateway_runs.py; a gateway killed
between requests and Redis or ingest gone for a minute: test_gateways.py.
"""
from __future__ import annotations

import json
import time

import pytest
from asgiref.sync import async_to_sync
from channels.routing import URLRouter
from channels.testing import WebsocketCommunicator
from django.conf import settings
from django.contrib.auth.models import User
from django.test import Client, override_settings
from django.utils import timezone

from lifecycle_site.audit.models import ParameterRecord, TransitionRecord
from lifecycle_site.dashboard.consumers import TRY_AGAIN_LATER
from lifecycle_site.dashboard.routing import websocket_urlpatterns
from lifecycle_site.fleet.models import Gateway, GroupRun, Robot
from lifecycle_site.gateway_link import gateways
from ros_gateway.shared import protocol
from tests import stack
from tests.conftest import make_user, session_of
from tests.integration.conftest import register, wait_node

NAME, ROBOT = "cell-f", "fault-agv"
USER = "fiona-operator"
# The gateway beats every 3 s, so its lease (3 beats) outlives a respawn's start on this slow
# machine by far; the site calls it offline 10 s after its last beat, as in production.
HEARTBEAT_S = "3.0"
OFFLINE_AFTER_S = 10.0
SLOW_S = 6.0  # flaky_node's slow configure
ANSWER_SLACK_S = 2.0  # beyond a request's documented bound (3 x timeout + 3 s): this machine is slow
# A gateway's stop: its bounded flush and farewell (ros_gateway/service.py), its ROS domains'
# shutdown, and slack for this machine. Docker's default grace before SIGKILL is 10 s.
GATEWAY_STOP_BOUND_S = 10.0


class Cell:
    """Gateway cell-f with robot fault-agv: lidar and camera in one process, a slow flaky_node
    in another."""

    def __init__(self) -> None:
        self.processes: list[stack.Process] = []
        self.gateway = self.start_gateway()

    def start_gateway(self) -> stack.Process:
        self.gateway = stack.start_gateway(NAME, LIFECYCLE_HEARTBEAT_INTERVAL=HEARTBEAT_S)
        self.processes.append(self.gateway)
        return self.gateway

    def start_robot(self, name: str, nodes: str, *params: str, namespace: str = "") -> stack.Process:
        process = stack.start_robot(name, stack.domain(10), nodes, *params, namespace=namespace)
        self.processes.append(process)
        return process


@pytest.fixture(scope="module")
def cell(redis_server, live_db, ingest):
    make_user(USER, "operator")  # once: the requests made side by side only log in
    with override_settings(LIFECYCLE={**settings.LIFECYCLE, "GATEWAY_OFFLINE_AFTER": OFFLINE_AFTER_S}):
        made = Cell()
        register(ROBOT, stack.domain(10), gateway=NAME)
        try:
            made.start_robot("fault-nodes", "lidar_driver,camera_driver")
            made.flaky = made.start_robot("fault-flaky", "flaky_node", "flaky_node.failure_mode:=slow_configure",
                                          f"flaky_node.slow_seconds:={SLOW_S}")
            for node in ("lidar_driver", "camera_driver", "flaky_node"):
                wait_node(None, key(node), alive=True, state="unconfigured", timeout=30)
            stack.wait_for(lambda: gateways.status(NAME).online, 20, f"gateway {NAME} online")
            yield made
        finally:
            for process in made.processes:
                process.stop()
            Robot.objects.filter(name=ROBOT).delete()
            Gateway.objects.filter(name=NAME).delete()


def key(node: str) -> str:
    return f"{ROBOT}.{node.strip('/').replace('/', '.')}"


def operator() -> Client:
    """A client of its own for each thread (a request made while the test injects a fault)."""
    client = Client()
    client.force_login(User.objects.get(username=USER))
    return client


def transition(node: str, name: str, **extra):
    return operator().post(f"/api/v1/nodes/{key(node)}/transition", {"transition": name, **extra},
                           content_type="application/json")


def patch(node: str, values: dict):
    return operator().patch(f"/api/v1/nodes/{key(node)}/parameters", json.dumps(values),
                            content_type="application/json")


def records(node: str, since, source: str = "api") -> list[TransitionRecord]:
    return list(TransitionRecord.objects.filter(node__key=key(node), source=source, requested_at__gte=since)
                .order_by("id"))


def gateway_online() -> bool:
    gateways.forget()  # read its beat afresh
    return gateways.status(NAME).online


def test_commands_queued_at_a_frozen_gateway_expire_on_record_and_are_not_carried_out(cell, settings):
    # The site waits 3 x 1 + 3 = 6 s for each of these.
    settings.LIFECYCLE = {**settings.LIFECYCLE, "SERVICE_TIMEOUT": 1.0}
    since = timezone.now()
    params_before = ParameterRecord.objects.filter(node__key=key("lidar_driver")).count()
    with stack.frozen(cell.gateway.pid):
        asked = timezone.now()
        calls = [stack.Timed(lambda: transition("lidar_driver", "configure")),
                 stack.Timed(lambda: transition("camera_driver", "configure")),
                 stack.Timed(lambda: patch("lidar_driver", {"scan_rate_hz": 10.0}))]
        answers = [call.result(6 + ANSWER_SLACK_S + 2) for call in calls]
    for call, answer in zip(calls, answers, strict=True):
        assert call.seconds < 6 + ANSWER_SLACK_S, f"answered after {call.seconds:.1f} s"
        error = answer.json()["error"]
        assert answer.status_code == 503 and error["code"] == "gateway_offline", error
        assert error["carried_out"] is False and "it was not carried out" in error["message"], error
    # Back by itself, and what it found queued (if anything) it did not carry out.
    stack.wait_for(gateway_online, 15, f"gateway {NAME} online again")
    time.sleep(1.5)  # what the gateway reports about expired commands reaches the ingest process
    made = records("lidar_driver", since) + records("camera_driver", since)
    assert len(made) == 2, [(r.node_name, r.outcome, r.error) for r in made]
    for record in made:
        assert record.outcome == "rejected" and "not carried out" in record.error
        assert abs((record.requested_at - asked).total_seconds()) < 1.0, "recorded at another time than asked"
        assert record.completed_at is None and record.duration_ms is None, "a made-up completion"
    rate = ParameterRecord.objects.filter(node__key=key("lidar_driver")).order_by("-id")
    assert rate.count() == params_before + 1
    assert (rate[0].name, rate[0].outcome) == ("scan_rate_hz", "rejected")
    assert abs((rate[0].at - asked).total_seconds()) < 1.0
    wait_node(None, key("lidar_driver"), state="unconfigured")
    values = {p["name"]: p["value"] for p in operator().get(f"/api/v1/nodes/{key('lidar_driver')}/parameters")
              .json()["parameters"]}
    assert values["scan_rate_hz"] == 5.0, "a command the user was told was not carried out was carried out"
    # The gateway carries out what comes now.
    assert transition("lidar_driver", "configure").status_code == 200


def test_a_gateway_killed_in_a_transition_is_answered_at_once_recorded_and_replaced_at_once(cell):
    since = timezone.now()
    flaky = cell.flaky
    began = flaky.output().count("configuring slowly")
    call = stack.Timed(lambda: transition("flaky_node", "configure", timeout=10))  # the site would wait 33 s
    stack.wait_for(lambda: flaky.output().count("configuring slowly") > began, 15, "the node configuring")
    cell.gateway.kill()
    killed = time.monotonic()
    replacement = cell.start_gateway()  # as a supervisor would, at once
    answer = call.result(20)
    assert call.seconds - (killed - call.began) < 4.0, f"answered {call.seconds:.1f} s after it was asked"
    error = answer.json()["error"]
    assert answer.status_code == 504 and error["code"] == "gateway_no_answer", error
    assert error["carried_out"] is None and "its process ended" in error["message"], error
    # The site did not call the dead gateway online meanwhile, and the respawn did not wait.
    state = gateways.status(NAME)
    assert state.online or "process has ended" in state.reason(), state
    stack.wait_for(gateway_online, 15, "the replacement online")
    assert "took over gateway 'cell-f'" in replacement.output(), replacement.output()[-2000:]
    # One record of the request, with the time it was asked and no invented outcome.
    made = records("flaky_node", since)
    assert [(r.outcome, r.completed_at, r.duration_ms) for r in made] == [("timed_out", None, None)], made
    assert "its process ended" in made[0].error
    # The node finished what it was sent, and the new gateway serves it.
    wait_node(None, key("flaky_node"), alive=True, state="inactive", timeout=SLOW_S + 10)
    assert transition("flaky_node", "cleanup").status_code == 200


def test_the_site_calls_a_killed_gateway_offline_at_once(cell):
    assert gateways.status(NAME).online  # seen connected by this process
    cell.gateway.kill()
    killed = time.monotonic()
    try:
        stack.wait_for(lambda: not gateways.status(NAME).online, 3, "the killed gateway shown offline")
        assert time.monotonic() - killed < 2.5
        assert "its process has ended" in gateways.status(NAME).reason()
        response = transition("lidar_driver", "cleanup")
        assert response.status_code == 503 and "process has ended" in response.json()["error"]["message"]
    finally:
        cell.start_gateway()
    stack.wait_for(gateway_online, 20, "the gateway back")


def test_a_robot_process_killed_in_a_transition_is_answered_within_its_bound_and_recorded(cell):
    robot = cell.start_robot("fault-flaky-k", "flaky_node", "flaky_node.failure_mode:=slow_configure",
                             f"flaky_node.slow_seconds:={SLOW_S}", namespace="/k")
    wait_node(None, key("k/flaky_node"), alive=True, state="unconfigured", timeout=30)
    since = timezone.now()
    call = stack.Timed(lambda: transition("k/flaky_node", "configure", timeout=2))
    stack.wait_for(lambda: "configuring slowly" in robot.output(), 15, "the node configuring")
    robot.kill()
    killed = time.monotonic()
    answer = call.result(20)
    # Its process is seen gone (on this host, at once): the answer does not wait for the timeout.
    assert time.monotonic() - killed < 2 + ANSWER_SLACK_S, f"answered {time.monotonic() - killed:.1f} s after the kill"
    error = answer.json()["error"]
    assert answer.status_code == 422 and error["code"] == "process_lost", error
    assert "process ended during configure" in error["message"], error
    made = records("k/flaky_node", since)
    assert [r.outcome for r in made] == ["process_lost"] and made[0].id == error["record_id"]
    wait_node(None, key("k/flaky_node"), alive=False, timeout=5)
    assert transition("k/flaky_node", "configure").json()["error"]["code"] == "node_offline"
    # Its supervisor starts it again: a new, unconfigured process under the same node.
    cell.start_robot("fault-flaky-k2", "flaky_node", namespace="/k")
    wait_node(None, key("k/flaky_node"), alive=True, state="unconfigured", timeout=30)
    assert transition("k/flaky_node", "configure").status_code == 200


def fleet_socket_close_code() -> int | None:
    """Open the fleet page's socket in this process, as daphne would; its close code, or None
    while it stays open."""
    user = make_user(USER, "operator")
    session = session_of(user)

    async def scenario() -> int | None:
        communicator = WebsocketCommunicator(URLRouter(websocket_urlpatterns), "/ws/fleet/")
        communicator.scope["user"] = user
        communicator.scope["session"] = session
        try:
            await communicator.connect(timeout=15)
            while True:
                message = await communicator.receive_output(timeout=15)
                if message["type"] == "websocket.close":
                    return message.get("code")
                if message["type"] == "websocket.send":
                    return None
        finally:
            await communicator.disconnect()

    return async_to_sync(scenario)()


def test_redis_frozen_or_stopped_every_request_answers_within_seconds_on_record_and_all_recovers(cell, redis_server):
    since = timezone.now()
    asked_runs = GroupRun.objects.filter(robot__name=ROBOT).count()
    params_before = ParameterRecord.objects.filter(node__key=key("camera_driver")).count()
    client = operator()
    # Frozen: connections stay open, nothing answers. Every read gives up after seconds.
    with stack.frozen(redis_server.current.pid):
        time.sleep(1.2)  # what this process read before is no longer trusted
        listing = stack.Timed(lambda: client.get("/api/v1/gateways"))
        assert listing.result(30).status_code == 200 and listing.seconds < 4 + ANSWER_SLACK_S, listing.seconds
        listed = {g["name"]: g for g in listing.result(1).json()["gateways"]}
        assert listed[NAME]["status"] == "unreachable", listed[NAME]
        refused = stack.Timed(lambda: transition("camera_driver", "configure"))
        assert refused.result(30).status_code == 503 and refused.seconds < 4 + ANSWER_SLACK_S, refused.seconds
    # Stopped: connections refused.
    redis_server.stop()
    try:
        began = time.monotonic()
        answers = [transition("camera_driver", "configure"), patch("camera_driver", {"fps": 8.0, "width": 80}),
                   client.post(f"/api/v1/robots/{ROBOT}/operations", {"operation": "bringup"},
                               content_type="application/json"),
                   client.get("/api/v1/gateways"), client.get("/"), client.get(f"/nodes/{key('camera_driver')}/")]
        assert time.monotonic() - began < 4 + ANSWER_SLACK_S
        assert [a.status_code for a in answers] == [503, 503, 503, 200, 200, 200], [a.content[:200] for a in answers]
        for answer in answers[:3]:
            assert "Redis" in answer.json()["error"]["message"] and "unreachable" in answer.json()["error"]["message"]
        assert fleet_socket_close_code() == TRY_AGAIN_LATER  # refused with a code the page retries on, not a 500
    finally:
        redis_server.start()
    # Back by itself: the gateway, live updates, commands; nothing restarted. The gateway's config,
    # lost with Redis's data, is there again for a gateway that starts now (not a minute later).
    stack.wait_for(gateway_online, 30, f"gateway {NAME} online after Redis came back")
    config = protocol.config_key(gateways.channel_prefix(), NAME)
    stack.wait_for(lambda: stack.redis_client().exists(config), 6, "the gateway's config in Redis again")
    assert fleet_socket_close_code() is None
    response = stack.wait_for(lambda: (r := transition("camera_driver", "configure")).status_code != 503 and r, 20,
                              "a command after Redis came back")
    assert response.status_code == 200, response.json()
    # Asked while Redis was frozen or stopped: 2 transitions, 2 parameters, 1 run; and the one after.
    made = records("camera_driver", since)
    assert [r.outcome for r in made] == ["rejected", "rejected", "succeeded"], [(r.outcome, r.error) for r in made]
    assert ParameterRecord.objects.filter(node__key=key("camera_driver")).count() == params_before + 2
    runs = GroupRun.objects.filter(robot__name=ROBOT).order_by("-created")
    assert runs.count() == asked_runs + 1 and runs[0].status == "failed" and "Redis" in runs[0].message


def test_a_gateway_stopped_while_redis_is_frozen_ends_within_seconds(cell, redis_server):
    """Stopping (docker stop, systemd) with Redis not answering: what the gateway still holds
    is given up after a bounded wait, not after every Redis call's own timeouts and retries
    (more than a minute), by which time a supervisor would have killed it."""
    with stack.frozen(redis_server.current.pid):
        began = time.monotonic()
        code = cell.gateway.stop(timeout=40)  # SIGTERM, and SIGKILL only after 40 s
        took = time.monotonic() - began
    assert code == 0 and took < GATEWAY_STOP_BOUND_S, (code, took, cell.gateway.output()[-1500:])
    assert "stopping without a last word to Redis (no answer within" in cell.gateway.output()
    cell.start_gateway()
    stack.wait_for(gateway_online, 30, f"gateway {NAME} online after its restart")
    for node in ("lidar_driver", "camera_driver", "flaky_node"):
        wait_node(None, key(node), alive=True, timeout=30)


def test_with_the_ingest_process_stopped_requests_are_on_record_before_their_answer_and_once(cell, ingest):
    stack.wait_for(lambda: stack.facts_read(NAME), 20, "the gateway's facts read by the ingest process")
    # (A Redis restart without persistence, as above, loses what the ingest process had not read yet.)
    lost_before = Gateway.objects.get(name=NAME).facts_lost
    since = timezone.now()
    state = wait_node(None, key("camera_driver"), alive=True).state_label
    step = {"unconfigured": "configure", "inactive": "activate", "active": "deactivate"}[state]
    ingest.stop()
    try:
        answer = transition("camera_driver", step)
        assert answer.status_code == 200, answer.json()
        assert TransitionRecord.objects.filter(id=answer.json()["record_id"]).exists()
        assert patch("camera_driver", {"fps": 9.0}).status_code == 200
    finally:
        ingest.start()
    # The ingest process then reads the same facts from the gateway's stream: nothing twice.
    stack.wait_for(lambda: stack.facts_read(NAME), 20, "the gateway's facts read by the ingest process")
    assert [r.transition_label for r in records("camera_driver", since)] == [step]
    assert ParameterRecord.objects.filter(node__key=key("camera_driver"), at__gte=since).count() == 1
    assert Gateway.objects.get(name=NAME).facts_lost == lost_before
