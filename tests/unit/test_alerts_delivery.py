"""Sending alerts: a real HTTP receiver on 127.0.0.1 (signature, retries with backoff, what is not
retried, the bounded queue) and Django's locmem mail backend; the delivery log and counters."""
from __future__ import annotations

import hashlib
import hmac
import json
import logging
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest
from django.core import mail
from django.utils import timezone

from lifecycle_site.alerts import lifecycle
from lifecycle_site.alerts.delivery import SIGNATURE_HEADER, Dispatcher
from lifecycle_site.alerts.engine import Evaluator, make_job, prune
from lifecycle_site.alerts.models import Alert, Delivery, Receiver, Rule
from lifecycle_site.fleet.models import Gateway, ManagedNode, Robot
from tests import stack
from tests.conftest import make_user

SECRET = "s3cret-for-tests-only"


class WebhookReceiver:
    """A real HTTP server in a thread: records each POST and answers with the next of ``answers``
    (then 200). ``hold`` (an Event) keeps each answer back until it is set."""

    def __init__(self, answers: tuple[int, ...] = (), hold: threading.Event | None = None) -> None:
        self.requests: list[dict] = []
        self.answers = list(answers)
        self.hold = hold
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802 - http.server's name
                body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
                receiver.requests.append({"headers": dict(self.headers), "body": body, "at": time.monotonic(),
                                          "path": self.path})
                if receiver.hold is not None:
                    receiver.hold.wait(10)
                status = receiver.answers.pop(0) if receiver.answers else 200
                self.send_response(status)
                self.send_header("Content-Length", "2")
                self.end_headers()
                self.wfile.write(b"ok")

            def log_message(self, *args) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.server.server_address[1]}/hook"

    def wait(self, count: int, timeout: float = 10.0) -> list[dict]:
        stack.wait_for(lambda: len(self.requests) >= count, timeout, f"{count} webhook requests")
        return self.requests

    def events(self) -> list[tuple[str, str]]:
        return [(json.loads(r["body"])["event"], json.loads(r["body"])["alert"]["subject"]) for r in self.requests]

    def close(self) -> None:
        if self.hold is not None:
            self.hold.set()
        self.server.shutdown()
        self.server.server_close()
        self.thread.join(5)


def signature_valid(request: dict, secret: str = SECRET) -> bool:
    expected = "sha256=" + hmac.new(secret.encode(), request["body"], hashlib.sha256).hexdigest()
    return hmac.compare_digest(request["headers"].get(SIGNATURE_HEADER, ""), expected)


@pytest.fixture
def fast_retries(settings):
    settings.ALERTS = {**settings.ALERTS, "RETRY_BASE_S": 0.2, "RETRY_CAP_S": 1.0, "ATTEMPTS": 3, "TIMEOUT_S": 2.0}
    return settings


@pytest.fixture
def receiver():
    hook = WebhookReceiver()
    yield hook
    hook.close()


@pytest.fixture
def finalized_node(db):
    robot = Robot.objects.create(name="dl-agv", domain_id=64, gateway=Gateway.objects.create(name="dl-cell"))
    now = timezone.now()
    return ManagedNode.objects.create(robot=robot, name="/planner", alive=True, state_label="finalized", state_id=4,
                                      first_seen=now, last_seen=now, state_changed=now)


def drain(evaluator: Evaluator, until, timeout: float = 10.0) -> None:
    stack.wait_for(lambda: evaluator.store_results() is None and until(), timeout, "the deliveries")


def test_firing_and_resolved_reach_a_real_webhook_signed_and_logged(finalized_node, receiver, fast_retries, caplog):
    caplog.set_level(logging.DEBUG)
    hook = Receiver.objects.create(name="ops-hook", url=receiver.url, secret=SECRET)
    rule = Rule.objects.create(name="finalized", kind=Rule.Kind.STATE, state="finalized")
    rule.receivers.add(hook)
    evaluator = Evaluator()
    try:
        evaluator.evaluate()
        first = receiver.wait(1)[0]
        body = json.loads(first["body"])
        assert body["event"] == "firing" and body["version"] == 1
        assert body["alert"]["subject"] == "dl-agv.planner" and body["alert"]["status"] == "firing"
        assert body["alert"]["summary"] == "Node /planner on robot dl-agv is finalized."
        assert first["headers"]["Content-Type"] == "application/json"
        assert first["headers"]["X-Lifecycle-Event"] == "firing"
        assert first["headers"]["X-Lifecycle-Delivery"] == body["delivery"]
        assert signature_valid(first) and not signature_valid(first, "another-secret")
        lifecycle.acknowledge(body["alert"]["id"], make_user("olga-operator", "operator"))
        ManagedNode.objects.filter(pk=finalized_node.pk).update(state_label="unconfigured")
        evaluator.evaluate()
        receiver.wait(2)
        assert receiver.events() == [("firing", "dl-agv.planner"), ("resolved", "dl-agv.planner")]
        resolved = json.loads(receiver.requests[1]["body"])["alert"]
        assert (resolved["status"], resolved["acknowledged_by"]) == ("resolved", "olga-operator")
        assert all(signature_valid(r) for r in receiver.requests)
        drain(evaluator, lambda: Delivery.objects.count() == 2)
    finally:
        evaluator.dispatcher.stop()
    assert set(Delivery.objects.values_list("event", "outcome", "attempt", "status_code")) == {
        ("firing", "delivered", 1, 200), ("resolved", "delivered", 1, 200)}
    assert Receiver.objects.get(pk=hook.pk).delivered == 2
    assert SECRET not in caplog.text


def test_a_failing_webhook_is_retried_with_growing_pauses_then_given_up(finalized_node, fast_retries):
    flaky = WebhookReceiver(answers=(503, 500, 200))
    dead = WebhookReceiver(answers=(502, 502, 502, 502))
    refusing = WebhookReceiver(answers=(404,))
    rule = Rule.objects.create(name="finalized", kind=Rule.Kind.STATE, state="finalized")
    for name, hook in (("flaky", flaky), ("dead", dead), ("refusing", refusing)):
        rule.receivers.add(Receiver.objects.create(name=name, url=hook.url))
    evaluator = Evaluator()
    try:
        evaluator.evaluate()
        flaky.wait(3)
        dead.wait(3)
        drain(evaluator, lambda: Delivery.objects.filter(outcome__in=("delivered", "failed")).count() == 3)
    finally:
        evaluator.dispatcher.stop()
        for hook in (flaky, dead, refusing):
            hook.close()
    pauses = [b["at"] - a["at"] for a, b in zip(flaky.requests, flaky.requests[1:], strict=False)]
    assert 0.15 < pauses[0] < pauses[1], pauses  # 0.2 s, then 0.4 s
    log = {name: list(Delivery.objects.filter(receiver_name=name).order_by("id").values_list("attempt", "outcome"))
           for name in ("flaky", "dead", "refusing")}
    assert log["flaky"] == [(1, "retrying"), (2, "retrying"), (3, "delivered")]
    assert log["dead"] == [(1, "retrying"), (2, "retrying"), (3, "failed")]
    assert log["refusing"] == [(1, "failed")]  # a 4xx is the receiver's refusal: not retried
    assert len(refusing.requests) == 1
    assert "answered HTTP 404" in Delivery.objects.get(receiver_name="refusing").error
    assert Receiver.objects.get(name="dead").failed == 1


def test_an_unreachable_webhook_is_reported_with_its_address(finalized_node, fast_retries):
    url = f"http://127.0.0.1:{stack.free_port()}/hook"
    rule = Rule.objects.create(name="finalized", kind=Rule.Kind.STATE, state="finalized")
    rule.receivers.add(Receiver.objects.create(name="nobody", url=url))
    evaluator = Evaluator()
    try:
        evaluator.evaluate()
        drain(evaluator, lambda: Delivery.objects.filter(outcome="failed").exists())
    finally:
        evaluator.dispatcher.stop()
    assert f"could not reach {url}" in Delivery.objects.filter(outcome="failed").get().error


def test_the_queue_is_bounded_and_counts_what_it_drops(finalized_node, settings):
    settings.ALERTS = {**settings.ALERTS, "QUEUE_SIZE": 1, "WORKERS": 1}
    hold = threading.Event()
    slow = WebhookReceiver(hold=hold)
    hook = Receiver.objects.create(name="slow", url=slow.url)
    rule = Rule.objects.create(name="finalized", kind=Rule.Kind.STATE, state="finalized")
    rule.receivers.add(hook)
    dispatcher = Dispatcher()
    evaluator = Evaluator(dispatcher)
    try:
        evaluator.evaluate()  # the worker takes it and waits for the slow receiver
        slow.wait(1)
        alert = Alert.objects.get()
        evaluator.notify(alert, rule, "firing")  # queued
        evaluator.notify(alert, rule, "firing")  # the queue is full: dropped
        assert dispatcher.pending() == 1 and dispatcher.dropped == 1
        hold.set()
        slow.wait(2)
        drain(evaluator, lambda: Delivery.objects.filter(outcome="delivered").count() == 2)
    finally:
        dispatcher.stop()
        slow.close()
    assert Delivery.objects.filter(outcome="dropped").count() == 1
    assert Receiver.objects.get(pk=hook.pk).dropped == 1


def test_alerts_by_email_through_djangos_mail(finalized_node, fast_retries):
    team = Receiver.objects.create(name="shift-team", kind=Receiver.Kind.EMAIL,
                                   emails="shift@example.invalid, lead@example.invalid")
    rule = Rule.objects.create(name="finalized", kind=Rule.Kind.STATE, state="finalized")
    rule.receivers.add(team)
    evaluator = Evaluator()
    try:
        evaluator.evaluate()
        stack.wait_for(lambda: len(mail.outbox) == 1, 10, "the e-mail")
        drain(evaluator, lambda: Delivery.objects.filter(outcome="delivered").exists())
    finally:
        evaluator.dispatcher.stop()
    message = mail.outbox[0]
    assert message.to == ["shift@example.invalid", "lead@example.invalid"]
    assert message.subject == "[FIRING] finalized: dl-agv.planner"
    assert "Node /planner on robot dl-agv is finalized." in message.body


def test_the_delivery_log_is_pruned_to_its_bound(finalized_node, settings):
    settings.ALERTS = {**settings.ALERTS, "DELIVERY_LOG_KEEP": 3}
    now = timezone.now()
    Delivery.objects.bulk_create(Delivery(receiver_name="x", event="firing", outcome="delivered", at=now)
                                 for _ in range(10))
    newest = list(Delivery.objects.order_by("-id").values_list("id", flat=True)[:3])
    prune()
    assert sorted(Delivery.objects.values_list("id", flat=True), reverse=True) == newest


def test_the_payload_links_to_the_alert_when_the_site_url_is_set(finalized_node, settings):
    settings.ALERTS = {**settings.ALERTS, "SITE_URL": "https://edge.plant/lifecycle"}
    rule = Rule.objects.create(name="finalized", kind=Rule.Kind.STATE, state="finalized")
    alert = Alert.objects.create(rule=rule, rule_name=rule.name, subject="dl-agv.planner", summary="s",
                                 since=timezone.now(), fired_at=timezone.now())
    job = make_job(Receiver(id=1, name="r", url="http://127.0.0.1:9/"), alert, "firing")
    assert json.loads(job.body)["alert"]["url"] == f"https://edge.plant/lifecycle/alerts/#alert-{alert.id}"
