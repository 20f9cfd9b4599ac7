"""One shape of a refusal (lifecycle_site/refusal.py), whoever refuses: the operations, the gateway
link, the alerts; the API renders each in its one error shape, the pages show its message."""
from __future__ import annotations

import pytest
from django.test import Client

from lifecycle_site.alerts.lifecycle import acknowledge
from lifecycle_site.fleet.models import Robot
from lifecycle_site.gateway_link.gateway_client import GatewayNoAnswer, GatewayOffline
from lifecycle_site.operations.runs import start_run
from lifecycle_site.refusal import Refusal
from tests.conftest import make_user


def test_every_refusal_has_code_message_status_and_the_apis_shape():
    offline = GatewayOffline("Gateway cell-a is offline.", "cell-a", since="2026-01-01T00:00:00+00:00")
    assert isinstance(offline, Refusal) and offline.status == 503
    assert offline.as_json() == {"error": {"code": "gateway_offline", "message": "Gateway cell-a is offline.",
                                           "since": "2026-01-01T00:00:00+00:00"}}
    assert GatewayNoAnswer("No answer.", "cell-a").as_json()["error"]["carried_out"] is None
    assert Refusal("robot_disabled", "Robot agv-1 is disabled.", 409).status == 409


@pytest.mark.django_db
def test_the_operations_and_the_alerts_refuse_with_it():
    robot = Robot.objects.create(name="refusing-agv", domain_id=96, enabled=False)
    with pytest.raises(Refusal) as refused:
        start_run(robot, "bringup", user=make_user("olga-operator", "operator"), source="cli")
    assert (refused.value.code, refused.value.status) == ("robot_disabled", 409)
    with pytest.raises(Refusal) as refused:
        acknowledge(123456, make_user("olga-operator", "operator"))
    assert (refused.value.code, refused.value.status) == ("not_found", 404)


@pytest.mark.django_db
def test_the_api_and_the_page_render_the_same_refusal(operator_client: Client):
    Robot.objects.create(name="refusing-agv", domain_id=96, enabled=False)
    api = operator_client.post("/api/v1/robots/refusing-agv/operations", {"operation": "bringup"},
                               content_type="application/json")
    assert api.status_code == 409
    message = api.json()["error"]["message"]
    assert api.json()["error"]["code"] == "robot_disabled" and "refusing-agv is disabled" in message
    page = operator_client.post("/robots/refusing-agv/operations", {"operation": "bringup"}, HTTP_HX_REQUEST="true")
    assert message in page.content.decode()


@pytest.mark.django_db
def test_a_body_that_is_not_an_object_is_refused_in_the_apis_shape(operator_client: Client):
    Robot.objects.create(name="refusing-agv", domain_id=96)
    for body, says in (("[1]", "must be a JSON object."), ("{", "is not valid JSON"), ("NaN", "not a finite")):
        answer = operator_client.post("/api/v1/robots/refusing-agv/operations", body,
                                      content_type="application/json")
        assert answer.status_code == 400 and says in answer.json()["error"]["message"], answer.content
