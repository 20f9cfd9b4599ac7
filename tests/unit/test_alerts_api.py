"""Alerts through the API, the pages, the admin and /metrics, by role: viewers see, operators
acknowledge, admins manage rules and receivers (whose secret is entered, never shown)."""
from __future__ import annotations

import ipaddress

import pytest
from django.test import Client
from django.utils import timezone
from prometheus_client.parser import text_string_to_metric_families

from lifecycle_site.alerts.engine import Evaluator
from lifecycle_site.alerts.models import Alert, Receiver, Rule
from lifecycle_site.fleet.models import Gateway, ManagedNode, Robot
from tests.conftest import client_of


@pytest.fixture
def firing(db) -> Alert:
    robot = Robot.objects.create(name="ap-agv", domain_id=65, gateway=Gateway.objects.create(name="ap-cell"))
    now = timezone.now()
    ManagedNode.objects.create(robot=robot, name="/planner", alive=True, state_label="finalized", state_id=4,
                               first_seen=now, last_seen=now, state_changed=now)
    Rule.objects.create(name="finalized", kind=Rule.Kind.STATE, state="finalized")
    Evaluator().evaluate()
    return Alert.objects.get()


def test_viewers_list_alerts_operators_acknowledge_them(firing):
    viewer, operator = client_of("vera-viewer", "viewer"), client_of("otto-operator", "operator")
    body = viewer.get("/api/v1/alerts").json()
    assert body["counts"] == {"firing": 1, "acknowledged": 0}
    assert [(a["subject"], a["status"], a["kind"]) for a in body["alerts"]] == [("ap-agv.planner", "firing", "state")]
    assert viewer.get(f"/api/v1/alerts/{firing.id}").json()["summary"] == "Node /planner on robot ap-agv is finalized."
    refused = viewer.post(f"/api/v1/alerts/{firing.id}/acknowledge")
    assert refused.status_code == 403 and "operator or admin needed" in refused.json()["error"]["message"]
    answer = operator.post(f"/api/v1/alerts/{firing.id}/acknowledge")
    assert answer.status_code == 200, answer.json()
    assert (answer.json()["status"], answer.json()["acknowledged_by"]) == ("acknowledged", "otto-operator")
    again = operator.post(f"/api/v1/alerts/{firing.id}/acknowledge").json()["error"]
    assert again["code"] == "already_acknowledged"
    assert operator.post("/api/v1/alerts/999999/acknowledge").status_code == 404
    assert viewer.get("/api/v1/alerts?status=acknowledged").json()["alerts"][0]["id"] == firing.id
    assert viewer.get("/api/v1/alerts?status=firing").json()["alerts"] == []
    assert viewer.get("/api/v1/alerts?status=nonsense").json()["error"]["code"] == "bad_status"
    assert Client().get("/api/v1/alerts").status_code == 401


def test_admins_manage_rules_through_the_api(db):
    Receiver.objects.create(name="ops-hook", url="http://127.0.0.1:9/hook", secret="k")
    admin, operator = client_of("ada-admin", "admin"), client_of("otto-operator", "operator")
    rule = {"name": "agv errors", "kind": "state", "state": "errorprocessing", "node_pattern": "/agv1/*",
            "receivers": ["ops-hook"], "keep_firing_seconds": 300}
    refused = operator.post("/api/v1/alert-rules", rule, content_type="application/json")
    assert refused.status_code == 403 and "admin needed" in refused.json()["error"]["message"]
    created = admin.post("/api/v1/alert-rules", rule, content_type="application/json")
    assert created.status_code == 201, created.json()
    made = created.json()
    assert (made["state"], made["receivers"], made["for_seconds"], made["enabled"]) == (
        "errorprocessing", ["ops-hook"], 0.0, True)
    changed = admin.patch(f"/api/v1/alert-rules/{made['id']}", {"for_seconds": 2, "enabled": False},
                          content_type="application/json")
    assert changed.status_code == 200, changed.json()
    assert (changed.json()["for_seconds"], changed.json()["enabled"], changed.json()["node_pattern"]) == (
        2.0, False, "/agv1/*")
    invalid = admin.post("/api/v1/alert-rules", {"name": "x", "kind": "state", "receivers": ["nobody"]},
                         content_type="application/json").json()["error"]
    assert invalid["code"] == "invalid_rule" and set(invalid["fields"]) == {"state", "receivers"}
    unknown = admin.post("/api/v1/alert-rules", {"name": "x", "kind": "gone", "severity": "high"},
                         content_type="application/json").json()["error"]
    assert unknown["code"] == "unknown_fields" and "severity" in unknown["message"]
    assert [r["name"] for r in operator.get("/api/v1/alert-rules").json()["rules"]] == [
        "Desired state not kept", "Mode not ready", "agv errors"]  # (the first two: alerts/installed_rules.py)
    assert operator.delete(f"/api/v1/alert-rules/{made['id']}").status_code == 403
    assert admin.delete(f"/api/v1/alert-rules/{made['id']}").json() == {"deleted": made["id"]}
    assert not Rule.objects.filter(name="agv errors").exists()


def test_the_page_lists_alerts_and_operators_acknowledge_with_htmx(firing):
    operator = client_of("otto-operator", "operator")
    page = operator.get("/alerts/").content.decode()
    assert f'id="alert-{firing.id}"' in page and "Acknowledge" in page
    assert 'id="alert-count"' in page and 'class="count" aria-label="1 firing">1<' in page
    row = operator.post(f"/alerts/{firing.id}/acknowledge", HTTP_HX_REQUEST="true",
                        HTTP_HX_TARGET=f"alert-{firing.id}").content.decode()
    assert "by otto-operator" in row and "Acknowledge</button>" not in row
    count = operator.get("/alerts/count").content.decode()
    assert 'aria-label="0 firing">0<' in count
    viewer = client_of("vera-viewer", "viewer")
    assert "Acknowledge</button>" not in viewer.get("/alerts/?status=all").content.decode()
    assert viewer.post(f"/alerts/{firing.id}/acknowledge").status_code == 403
    assert Client().get("/alerts/count").status_code == 286  # signed out: htmx stops polling
    fleet_page = viewer.get("/").content.decode()
    assert 'id="alert-count"' in fleet_page


def test_admins_enter_a_receivers_secret_that_is_never_shown(db):
    admin = client_of("ada-admin", "admin")
    form = {"name": "ops-hook", "kind": "webhook", "url": "https://hooks.example.invalid/a", "secret": "hidden-key-1",
            "emails": "", "enabled": "on"}
    assert admin.post("/admin/alerts/receiver/add/", form).status_code == 302
    receiver = Receiver.objects.get()
    assert receiver.secret == "hidden-key-1"
    page = admin.get(f"/admin/alerts/receiver/{receiver.pk}/change/").content.decode()
    assert "hidden-key-1" not in page
    assert admin.post(f"/admin/alerts/receiver/{receiver.pk}/change/", {**form, "secret": ""}).status_code == 302
    assert Receiver.objects.get().secret == "hidden-key-1"  # left empty: kept
    bad = admin.post("/admin/alerts/receiver/add/", {**form, "name": "ftp", "url": "ftp://x.example.invalid/"})
    assert "Enter a valid URL" in bad.content.decode()
    assert admin.get("/admin/alerts/rule/add/").status_code == 200
    rule = {"name": "drivers finalized", "enabled": "on", "kind": "state", "state": "finalized",
            "for_seconds": "0", "keep_firing_seconds": "0", "node_pattern": "/agv1/*_driver",
            "receivers": [str(receiver.pk)]}
    assert admin.post("/admin/alerts/rule/add/", rule).status_code == 302
    saved = Rule.objects.get(name="drivers finalized")
    assert (saved.kind, saved.state, saved.node_pattern, list(saved.receivers.all())) == (
        "state", "finalized", "/agv1/*_driver", [receiver])
    no_state = admin.post("/admin/alerts/rule/add/", {**rule, "name": "no state", "state": ""})
    assert "Choose the state this rule watches for." in no_state.content.decode()
    gateway_pattern = admin.post("/admin/alerts/rule/add/", {**rule, "name": "gw", "kind": "gateway_offline",
                                                              "state": ""})
    assert "A gateway rule has no node pattern." in gateway_pattern.content.decode()
    assert not Rule.objects.filter(name__in=["no state", "gw"]).exists()
    assert admin.get("/admin/alerts/delivery/").status_code == 200
    assert client_of("otto-operator", "operator").get("/admin/alerts/rule/").status_code == 302  # not staff


def test_metrics_show_alerts_firing(firing, client, settings):
    settings.LIFECYCLE_METRICS_ALLOW = [ipaddress.ip_network("127.0.0.0/8")]
    samples = {(s.name, tuple(sorted(s.labels.items()))): s.value
               for f in text_string_to_metric_families(client.get("/metrics").content.decode()) for s in f.samples}
    assert samples[("lifecycle_alerts_firing", (("rule", "finalized"), ("status", "firing")))] == 1
    assert samples[("lifecycle_alerts_firing", (("rule", "finalized"), ("status", "acknowledged")))] == 0
