"""/healthz, /readyz and /metrics (lifecycle_site.monitoring) against a real Redis and database."""
from __future__ import annotations

import time
from datetime import timedelta

import pytest
from django.test import Client
from django.utils import timezone
from prometheus_client.parser import text_string_to_metric_families

from lifecycle_site.api.models import ApiToken
from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import Gateway, GroupRun, ManagedNode, Robot
from tests import stack
from tests.conftest import make_user


def metrics(text: str) -> dict[tuple[str, tuple], float]:
    """Every sample as {(name, sorted labels): value}."""
    return {
        (sample.name, tuple(sorted(sample.labels.items()))): sample.value
        for family in text_string_to_metric_families(text)
        for sample in family.samples
    }


@pytest.fixture
def fleet(db, redis_server) -> Robot:
    gateway = Gateway.objects.create(name="mon-cell", backlog=7, logs_received=1200, logs_dropped=30, logs_lost=2,
                                     facts_lost=1, facts_rejected=4)
    robot = Robot.objects.create(name="mon-agv", domain_id=44, gateway=gateway)
    now = timezone.now()
    for name, state, alive in (("/lidar", "active", True), ("/camera", "active", True),
                               ("/planner", "inactive", True), ("/old", "unconfigured", False)):
        ManagedNode.objects.create(robot=robot, name=name, state_label=state, alive=alive, last_seen=now)
    lidar = ManagedNode.objects.get(name="/lidar")
    for outcome, duration_ms in (("succeeded", 3.0), ("succeeded", 40.0), ("failed", 700.0), ("rejected", 0.0)):
        TransitionRecord.objects.create(
            node=lidar, robot=robot, robot_name=robot.name, node_name=lidar.name, transition_label="activate",
            outcome=outcome, source="api", requested_at=now - timedelta(seconds=1), completed_at=now,
            duration_ms=duration_ms,
        )
    return robot


def test_healthz_answers_without_login(client: Client):
    answer = client.get("/healthz")
    assert answer.status_code == 200 and answer.json() == {"status": "ok"}
    assert "no-store" in answer["Cache-Control"]


def test_readyz_reports_database_redis_ingest_and_gateways(fleet, client: Client):
    body = client.get("/readyz").json()
    assert body["database"] == "ok" and body["redis"] == "ok"
    assert body["gateways"] == {"with_robots": 1, "online": 0, "quarantined": 0}  # it never beat
    assert body["status"] == "degraded"


def test_readyz_is_503_within_its_bound_when_redis_is_gone(fleet, client: Client, settings):
    settings.REDIS_URL = f"redis://127.0.0.1:{stack.free_port()}/0"  # nobody listens there
    began = time.monotonic()
    answer = client.get("/readyz")
    assert time.monotonic() - began < 5
    assert answer.status_code == 503
    assert answer.json()["redis"] == "unavailable" and answer.json()["status"] == "unavailable"


def test_metrics_need_a_token_or_an_allowed_address(fleet, client: Client, settings):
    refused = client.get("/metrics")
    assert refused.status_code == 401 and refused.json()["error"]["code"] == "unauthorized"
    assert client.get("/metrics", HTTP_AUTHORIZATION="Bearer not-a-token").status_code == 401
    _, token = ApiToken.issue(make_user("prometheus", "viewer"), "scrape")
    assert client.get("/metrics", HTTP_AUTHORIZATION=f"Bearer {token}").status_code == 200
    settings.LIFECYCLE_METRICS_ALLOW = [__import__("ipaddress").ip_network("127.0.0.0/8")]
    assert client.get("/metrics").status_code == 200  # the test client's REMOTE_ADDR is 127.0.0.1
    assert client.get("/metrics", REMOTE_ADDR="10.1.2.3").status_code == 401


def test_metrics_count_nodes_gateways_and_transitions(fleet, client: Client, settings):
    settings.LIFECYCLE_METRICS_ALLOW = [__import__("ipaddress").ip_network("127.0.0.1/32")]
    answer = client.get("/metrics")
    assert answer["Content-Type"].startswith("text/plain")
    samples = metrics(answer.content.decode())
    labels = (("gateway", "mon-cell"), ("robot", "mon-agv"))

    def nodes(state: str) -> float:
        return samples.get(("lifecycle_nodes", tuple(sorted((*labels, ("state", state))))), 0)

    assert (nodes("active"), nodes("inactive"), nodes("not_running")) == (2, 1, 1)
    cell = (("gateway", "mon-cell"),)
    assert samples[("lifecycle_gateway_online", cell)] == 0
    assert ("lifecycle_gateway_heartbeat_age_seconds", cell) not in samples  # it never beat
    assert samples[("lifecycle_gateway_backlog", cell)] == 7
    assert samples[("lifecycle_log_records_received_total", cell)] == 1200
    assert samples[("lifecycle_log_records_dropped_total", cell)] == 30
    assert samples[("lifecycle_log_batches_lost_total", cell)] == 2
    assert samples[("lifecycle_gateway_facts_lost_total", cell)] == 1
    assert samples[("lifecycle_gateway_facts_rejected_total", cell)] == 4
    assert samples[("lifecycle_transitions_total", (("outcome", "succeeded"), ("source", "api")))] == 2
    assert samples[("lifecycle_transitions_total", (("outcome", "rejected"), ("source", "api")))] == 1
    # Rejected attempts never reached a node: three durations, 3 ms, 40 ms, 700 ms.
    assert samples[("lifecycle_transition_duration_seconds_count", ())] == 3
    assert samples[("lifecycle_transition_duration_seconds_bucket", (("le", "0.005"),))] == 1
    assert samples[("lifecycle_transition_duration_seconds_bucket", (("le", "0.05"),))] == 2
    assert samples[("lifecycle_transition_duration_seconds_bucket", (("le", "1.0"),))] == 3
    assert samples[("lifecycle_transition_duration_seconds_sum", ())] == pytest.approx(0.743)
    assert samples[("lifecycle_group_runs_active", (("status", "running"),))] == 0
    for n, (operation, status) in enumerate([("bringup", "succeeded"), ("bringup", "succeeded"),
                                             ("restart", "partial"), ("shutdown", "running")]):
        GroupRun.objects.create(id=f"{n:032x}", robot=fleet, operation=operation, status=status)
    samples = metrics(client.get("/metrics").content.decode())
    assert samples[("lifecycle_group_runs_ended_total", (("operation", "bringup"), ("status", "succeeded")))] == 2
    assert samples[("lifecycle_group_runs_ended_total", (("operation", "restart"), ("status", "partial")))] == 1
    assert samples[("lifecycle_group_runs_ended_total", (("operation", "shutdown"), ("status", "failed")))] == 0
    assert samples[("lifecycle_group_runs_active", (("status", "running"),))] == 1


def test_a_bad_allow_list_stops_the_site_with_the_value_named(monkeypatch):
    from django.core.exceptions import ImproperlyConfigured

    from lifecycle_site.settings import _networks

    monkeypatch.setenv("LIFECYCLE_METRICS_ALLOW", "127.0.0.1, 10.0.0.0/33")
    with pytest.raises(ImproperlyConfigured, match="'10.0.0.0/33'"):
        _networks("LIFECYCLE_METRICS_ALLOW")
