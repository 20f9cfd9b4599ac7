"""Refused attempts are on record where an admin reviews them: who (account or address),
what, when, why; the newest 10,000 are kept."""
from __future__ import annotations

import pytest
from django.test import Client

from lifecycle_site.audit import denials
from lifecycle_site.audit.models import AccessDenial
from lifecycle_site.fleet.models import ManagedNode, Robot
from ros_gateway.shared import state_machine as sm
from tests.conftest import client_of, make_user


@pytest.fixture
def node(db) -> ManagedNode:
    robot = Robot.objects.create(name="deny-agv", domain_id=99)
    return ManagedNode.objects.create(robot=robot, name="/lidar", alive=True, state_id=sm.UNCONFIGURED,
                                      state_label="unconfigured")


def only() -> AccessDenial:
    rows = list(AccessDenial.objects.all())
    assert len(rows) == 1, rows
    return rows[0]


def test_a_viewer_changing_a_node_through_the_api_is_on_record(viewer_client, node):
    response = viewer_client.post(f"/api/v1/nodes/{node.key}/transition", {"transition": "configure"},
                                  content_type="application/json", REMOTE_ADDR="10.1.2.3")
    assert response.status_code == 403
    row = only()
    assert (row.username, row.user.username, row.client, row.method, row.status, row.code) == (
        "victor-viewer", "victor-viewer", "10.1.2.3", "POST", 403, "forbidden")
    assert row.path == f"/api/v1/nodes/{node.key}/transition" and "operator" in row.detail


def test_a_viewer_using_the_dashboard_buttons_is_on_record(viewer_client, node):
    response = viewer_client.post(f"/nodes/{node.key}/transition", {"transition": "configure"})
    assert response.status_code == 403
    assert (only().code, only().username) == ("forbidden", "victor-viewer")


def test_a_bad_token_is_on_record_even_for_reading_and_anonymous_reads_are_not(node):
    assert Client().get("/api/v1/nodes").status_code == 401
    assert not AccessDenial.objects.exists()
    assert Client().get("/api/v1/nodes", HTTP_AUTHORIZATION="Bearer guessed-token").status_code == 401
    assert only().code == "bad_token"
    assert Client().post(f"/api/v1/nodes/{node.key}/transition", {"transition": "configure"},
                         content_type="application/json").status_code == 401
    assert AccessDenial.objects.filter(code="unauthorized", method="POST").count() == 1


def test_a_session_write_without_csrf_is_on_record(node):
    client = Client(enforce_csrf_checks=True)
    client.force_login(make_user("olga-operator", "operator"))
    response = client.post(f"/api/v1/nodes/{node.key}/transition", {"transition": "configure"},
                           content_type="application/json")
    assert response.status_code == 403
    assert (only().code, only().username) == ("csrf_failed", "olga-operator")
    response = client.post(f"/nodes/{node.key}/transition", {"transition": "configure"})  # a form post
    assert response.status_code == 403
    assert AccessDenial.objects.filter(code="csrf_failed", path=f"/nodes/{node.key}/transition").exists()


def test_failed_logins_are_on_record_with_the_name_tried(db):
    make_user("olga-operator", "operator")
    response = Client().post("/login/", {"username": "olga-operator", "password": "wrong"}, REMOTE_ADDR="10.9.8.7")
    assert response.status_code == 200
    row = only()
    assert (row.code, row.username, row.client, row.user) == ("login_failed", "olga-operator", "10.9.8.7", None)
    Client().post("/admin/login/", {"username": "nobody", "password": "x"})
    assert AccessDenial.objects.filter(code="login_failed", username="nobody").exists()


def test_the_record_is_bounded(db):
    for i in range(30):
        denials.record(None, 401, "bad_token", username=f"u{i}")
    assert denials.prune(keep=10) == 20
    kept = list(AccessDenial.objects.order_by("id").values_list("username", flat=True))
    assert kept == [f"u{i}" for i in range(20, 30)]


def test_admins_review_them_in_the_admin_and_cannot_change_them(db):
    denials.record(None, 401, "bad_token", username="mallory")
    admin = client_of("ada-admin", "admin")
    page = admin.get("/admin/audit/accessdenial/")
    assert page.status_code == 200 and "mallory" in page.content.decode()
    row = AccessDenial.objects.get()
    assert admin.post(f"/admin/audit/accessdenial/{row.pk}/delete/", {"post": "yes"}).status_code == 403
    assert AccessDenial.objects.filter(username="mallory").count() == 1
    assert AccessDenial.objects.filter(username="ada-admin", code="forbidden").exists()  # that try, too
    viewer = client_of("victor-viewer", "viewer")
    assert viewer.get("/admin/audit/accessdenial/").status_code == 302  # not staff: to the admin login

