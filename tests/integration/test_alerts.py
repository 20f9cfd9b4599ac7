"""Alerts on the real stack: a gateway of this module's own, a robot process with real rclpy
lifecycle nodes, the site's ingest process (which evaluates the rules), and a real HTTP receiver
on 127.0.0.1. A node that passes through errorprocessing, one driven to finalized, a robot
process stopped and a gateway stopped: each alert fires, reaches the webhook with a valid
signature, and resolves when its condition is over."""
from __future__ import annotations

import json
import time

import pytest

from lifecycle_site.alerts.models import Alert, Delivery, Receiver, Rule
from lifecycle_site.fleet.models import Gateway, Robot
from tests import stack
from tests.integration.conftest import register, transition, wait_node
from tests.unit.test_alerts_delivery import SECRET, WebhookReceiver, signature_valid

GATEWAY, ROBOT, OFFSET = "al-gw", "al-agv", 27
FLAKY, LIDAR = f"{ROBOT}.flaky_node", f"{ROBOT}.lidar_driver"
WAIT_S = 20.0


def start_robot() -> stack.Process:
    return stack.start_robot("al-agv-nodes", stack.domain(OFFSET), "flaky_node,lidar_driver",
                             "flaky_node.failure_mode:=raise_activate")


@pytest.fixture(scope="module")
def hook(live_db):
    receiver = WebhookReceiver()
    yield receiver
    receiver.close()


@pytest.fixture(scope="module")
def cell(hook, redis_server, ingest):
    robot = register(ROBOT, stack.domain(OFFSET), gateway=GATEWAY)
    gateway = Gateway.objects.get(name=GATEWAY)
    target = Receiver.objects.create(name="al-hook", url=hook.url, secret=SECRET)
    rules = [
        Rule.objects.create(name="al-errors", kind=Rule.Kind.STATE, state="errorprocessing", robot=robot),
        Rule.objects.create(name="al-finalized", kind=Rule.Kind.STATE, state="finalized", robot=robot),
        Rule.objects.create(name="al-gone", kind=Rule.Kind.GONE, robot=robot),
        Rule.objects.create(name="al-offline", kind=Rule.Kind.GATEWAY_OFFLINE, gateway=gateway, for_seconds=1),
    ]
    for rule in rules:
        rule.receivers.add(target)
    processes = {"gateway": stack.start_gateway(GATEWAY)}
    processes["robot"] = start_robot()
    for key in (FLAKY, LIDAR):
        wait_node(None, key, alive=True, state="unconfigured", timeout=30)
    yield processes
    for process in processes.values():
        process.stop()
    # The session's ingest process evaluates rules: these go, and later tests see no trace of the cell.
    Rule.objects.filter(pk__in=[r.pk for r in rules]).delete()
    Alert.objects.filter(rule_name__startswith="al-").delete()
    target.delete()
    Robot.objects.filter(name=ROBOT).delete()
    Gateway.objects.filter(name=GATEWAY).delete()


def wait_event(hook: WebhookReceiver, event: str, rule: str, subject: str, timeout: float = WAIT_S) -> dict:
    """The webhook request telling ``event`` of the rule's alert about ``subject`` (its signature checked)."""

    def found():
        for request in list(hook.requests):
            body = json.loads(request["body"])
            alert = body["alert"]
            if (body["event"], alert["rule"], alert["subject"]) == (event, rule, subject):
                assert signature_valid(request), "the webhook's signature does not match its body"
                return {**body, "received": request["at"]}
        return None

    return stack.wait_for(found, timeout, f"the webhook to be told {event} {rule} {subject}")


def test_a_node_passing_through_errorprocessing_fires_and_resolves(api, cell, hook):
    assert transition(api, FLAKY, "configure").status_code == 200
    began = time.monotonic()
    answer = transition(api, FLAKY, "activate").json()["error"]
    assert answer["state"]["label"] == "unconfigured", answer  # raised: on_error brought it back
    fired = wait_event(hook, "firing", "al-errors", FLAKY)
    print(f"[alerts] errorprocessing: webhook told {fired['received'] - began:.2f} s after the activate request")
    # Seen in the facts the ingest process stored: the database held errorprocessing for milliseconds.
    assert fired["alert"]["summary"] == f"Node /flaky_node on robot {ROBOT} entered errorprocessing."
    resolved = wait_event(hook, "resolved", "al-errors", FLAKY)
    assert resolved["alert"]["id"] == fired["alert"]["id"] and resolved["alert"]["resolved_at"]
    assert Alert.objects.get(pk=fired["alert"]["id"]).status == "resolved"


def test_finalized_and_a_stopped_robot_process_fire_and_resolve(api, cell, hook):
    changed = api.patch(f"/api/v1/nodes/{FLAKY}/parameters", {"failure_mode": "error_in_error"},
                        content_type="application/json")
    assert changed.status_code == 200, changed.content
    assert transition(api, FLAKY, "configure").status_code == 200
    began = time.monotonic()
    assert transition(api, FLAKY, "activate").json()["error"]["state"]["label"] == "finalized"
    fired = wait_event(hook, "firing", "al-finalized", FLAKY)
    print(f"[alerts] finalized: webhook told {fired['received'] - began:.2f} s after the activate request")

    stopped = time.monotonic()
    assert cell["robot"].stop() == 0
    gone = wait_event(hook, "firing", "al-gone", LIDAR)
    wait_event(hook, "firing", "al-gone", FLAKY)
    print(f"[alerts] robot process stopped: webhook told {gone['received'] - stopped:.2f} s later")
    assert gone["alert"]["summary"] == f"Node /lidar_driver on robot {ROBOT} left the ROS graph: its process ended " \
                                       "or was stopped."
    wait_event(hook, "resolved", "al-finalized", FLAKY)  # a node that is gone is in no state

    cell["robot"] = start_robot()
    back = wait_event(hook, "resolved", "al-gone", LIDAR)
    wait_event(hook, "resolved", "al-gone", FLAKY)
    assert back["alert"]["id"] == gone["alert"]["id"]


def test_a_stopped_gateway_fires_after_its_delay_and_resolves_when_it_is_back(cell, hook):
    stopped = time.monotonic()
    assert cell["gateway"].stop() == 0
    fired = wait_event(hook, "firing", "al-offline", GATEWAY)
    took = fired["received"] - stopped
    print(f"[alerts] gateway stopped: webhook told {took:.2f} s later (rule: offline for 1 s)")
    assert took >= 0.9 and fired["alert"]["gateway"] == GATEWAY  # not before its delay
    assert f"Gateway {GATEWAY} is offline (it stopped at" in fired["alert"]["summary"]
    cell["gateway"] = stack.start_gateway(GATEWAY)
    restarted = time.monotonic()
    resolved = wait_event(hook, "resolved", "al-offline", GATEWAY)
    print(f"[alerts] gateway back: resolved {resolved['received'] - restarted:.2f} s after its restart")
    wait_node(None, LIDAR, alive=True, timeout=30)


def test_every_request_the_receiver_got_is_in_the_delivery_log(cell, hook):
    def logged() -> bool:
        return Delivery.objects.filter(receiver_name="al-hook", outcome="delivered").count() >= len(hook.requests)

    stack.wait_for(logged, 10, "the delivery log")
    assert not Delivery.objects.filter(receiver_name="al-hook").exclude(outcome="delivered").exists()
    assert Receiver.objects.get(name="al-hook").delivered == len(hook.requests)
