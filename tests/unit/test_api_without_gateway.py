"""API validation and error paths that need no ROS: bad input is refused clearly and
loses nothing; a missing gateway or Redis is reported, not a 500."""
import json
import time
from datetime import timedelta

import pytest
from django.core.management import call_command
from django.test import Client
from django.utils import timezone

from lifecycle_site.audit.models import AppendOnlyError, TransitionRecord
from lifecycle_site.fleet.models import ManagedNode, Robot
from lifecycle_site.gateway_link import gateways
from ros_gateway.shared import state_machine as sm
from tests import stack


@pytest.fixture
def node(db) -> ManagedNode:
    robot = Robot.objects.create(name="unit-agv", domain_id=99)
    return ManagedNode.objects.create(
        robot=robot, name="/joy_to_vel", alive=True, state_id=sm.UNCONFIGURED, state_label="unconfigured"
    )


def post(client: Client, node: ManagedNode, body, **extra):
    data = body if isinstance(body, (str, bytes)) else json.dumps(body)
    return client.post(f"/api/v1/nodes/{node.key}/transition", data, content_type="application/json", **extra)


def error_code(response) -> str:
    return response.json()["error"]["code"]


def test_node_ids_are_url_safe_and_distinct_per_robot(db):
    a = Robot.objects.create(name="agv-a", domain_id=1)
    b = Robot.objects.create(name="agv-b", domain_id=2)
    first = ManagedNode.objects.create(robot=a, name="/arm/gripper")
    second = ManagedNode.objects.create(robot=b, name="/arm/gripper")
    assert (first.key, second.key) == ("agv-a.arm.gripper", "agv-b.arm.gripper")


def test_unauthenticated_requests_get_401(node):
    for response in (Client().get("/api/v1/nodes"), post(Client(), node, {"transition": "configure"})):
        assert response.status_code == 401 and error_code(response) == "unauthorized"
    bad_token = Client().get("/api/v1/robots", HTTP_AUTHORIZATION="Bearer nonsense")
    assert bad_token.status_code == 401


def test_viewer_may_read_but_not_operate(viewer_client, node):
    assert viewer_client.get("/api/v1/nodes").status_code == 200
    response = post(viewer_client, node, {"transition": "configure"})
    assert response.status_code == 403 and error_code(response) == "forbidden"


@pytest.mark.parametrize(
    "body, code",
    [
        ('{"transition": ', "malformed_json"),
        (b"\xff\xfe", "malformed_json"),
        ("[1, 2]", "missing_field"),
        ({"transitio": "configure"}, "missing_field"),
        ({"transition": ["configure"]}, "invalid_field"),
        ({"transition": True}, "invalid_field"),
        ({"transition": "explode"}, "unknown_transition"),
        ({"transition": 42}, "unknown_transition"),
        ({"transition": "configure", "timeout": -1}, "invalid_field"),
        ('{"transition": "configure", "timeout": 1%s}' % ("0" * 400), "invalid_field"),
    ],
)
def test_malformed_requests_get_400_with_a_readable_message(operator_client, node, body, code):
    response = post(operator_client, node, body)
    assert response.status_code == 400
    assert error_code(response) == code and response.json()["error"]["message"]
    assert not TransitionRecord.objects.exists()


def test_unknown_node_is_404_in_json(operator_client, db):
    response = operator_client.post(
        "/api/v1/nodes/nope.nothing/transition", '{"transition": "configure"}', content_type="application/json"
    )
    assert response.status_code == 404 and error_code(response) == "not_found"
    assert operator_client.get("/api/v1/nodes/nope.nothing/logs").status_code == 404
    assert operator_client.get("/api/v1/nodes?robot=ghost").status_code == 404


def test_gateway_offline_is_503_and_the_attempt_is_audited(operator_client, node, redis_server):
    response = post(operator_client, node, {"transition": "configure"})
    assert response.status_code == 503 and error_code(response) == "gateway_offline"
    message = "Gateway local is offline (it has never reported); nothing was sent to unit-agv."
    assert response.json()["error"]["message"] == message
    record = TransitionRecord.objects.get()
    assert (record.outcome, record.source, record.requested_by_name) == ("rejected", "api", "olga-operator")
    assert record.error == message


def test_redis_down_is_503_not_500(operator_client, node, settings):
    settings.REDIS_URL = "redis://127.0.0.1:1/0"  # nothing listens there
    response = post(operator_client, node, {"transition": "configure"})
    assert response.status_code == 503 and "Redis" in response.json()["error"]["message"]
    assert "unit-agv" in response.json()["error"]["message"]


def test_stale_heartbeat_counts_as_offline(db, redis_server):
    stack.write_beat("gw", at=time.time() - 300)
    state = gateways.status("gw")
    assert not state.online and state.state == "offline"
    assert state.refusal("agv-3").startswith("Gateway gw is offline (no heartbeat since ")
    assert state.refusal("agv-3").endswith(", 5 min ago); nothing was sent to agv-3.")


def test_transition_on_a_node_that_is_gone_is_409_and_audited(operator_client, node):
    node.alive = False
    node.save()
    response = post(operator_client, node, {"transition": "configure"})
    assert response.status_code == 409 and error_code(response) == "node_offline"
    assert TransitionRecord.objects.get().outcome == "rejected"


def test_audit_records_are_append_only(node):
    now = timezone.now()
    record = TransitionRecord.objects.create(
        robot_name="unit-agv", node_name="/joy_to_vel", outcome="succeeded", source="api", requested_at=now
    )
    with pytest.raises(AppendOnlyError):
        record.save()
    with pytest.raises(AppendOnlyError):
        record.delete()
    with pytest.raises(AppendOnlyError):
        TransitionRecord.objects.all().delete()
    with pytest.raises(AppendOnlyError):
        TransitionRecord.objects.update(outcome="failed")
    assert TransitionRecord.objects.get().outcome == "succeeded"


def test_session_auth_needs_csrf_for_writes(node):
    from tests.conftest import make_user

    client = Client(enforce_csrf_checks=True)
    client.force_login(make_user("csrf-op", "operator"))
    response = post(client, node, {"transition": "configure"})
    assert response.status_code == 403 and error_code(response) == "csrf_failed"


def test_bearer_token_from_the_command_line_authenticates(db, capsys):
    from tests.conftest import make_user

    make_user("robot-ci", "viewer")
    call_command("create_api_token", "robot-ci")
    token = capsys.readouterr().out.strip()
    response = Client().get("/api/v1/robots", HTTP_AUTHORIZATION=f"Bearer {token}")
    assert response.status_code == 200 and "robots" in response.json()


def test_add_robot_command_registers_and_validates(db):
    from django.core.management.base import CommandError

    call_command("add_robot", "agv-9", "--domain", "7", "--namespace", "/agv9/")
    robot = Robot.objects.get(name="agv-9")
    assert (robot.domain_id, robot.namespace, robot.enabled) == (7, "/agv9", True)
    with pytest.raises(CommandError, match="domain_id"):
        call_command("add_robot", "agv-10", "--domain", "500")
    with pytest.raises(CommandError, match="lower-case"):
        call_command("add_robot", "AGV 10", "--domain", "5")


def test_logs_endpoint_filters_by_level(operator_client, node):
    from lifecycle_site.fleet.models import LogRecord

    for level, text in ((20, "hello"), (30, "careful"), (40, "broken")):
        LogRecord.objects.create(robot=node.robot, node=node, logger="joy_to_vel", stamp=timezone.now(),
                                 level=level, message=text)
    records = operator_client.get(f"/api/v1/nodes/{node.key}/logs?level=WARN").json()["records"]
    assert [r["message"] for r in records] == ["careful", "broken"]
    assert operator_client.get(f"/api/v1/nodes/{node.key}/logs?level=LOUD").status_code == 400


def test_log_history_is_pruned_by_count_per_logger_and_by_age(db):

    from lifecycle_site.fleet.models import LogRecord
    from lifecycle_site.ingest.log_store import prune_logs

    robot = Robot.objects.create(name="chatty", domain_id=98)
    now = timezone.now()
    LogRecord.objects.bulk_create(
        [LogRecord(robot=robot, logger="talker", stamp=now, level=20, message=f"m{i}") for i in range(30)]
        + [LogRecord(robot=robot, logger="quiet", stamp=now, level=20, message="q")]
        + [LogRecord(robot=robot, logger="old", stamp=now - timedelta(hours=5), level=20, message="o")]
    )
    deleted = prune_logs(keep_per_logger=10, keep_hours=1)
    assert deleted == 21
    kept = list(LogRecord.objects.filter(logger="talker").order_by("id").values_list("message", flat=True))
    assert kept == [f"m{i}" for i in range(20, 30)]  # the newest ten
    assert LogRecord.objects.filter(logger="quiet").count() == 1
    assert not LogRecord.objects.filter(logger="old").exists()


def test_admin_role_opens_the_admin_site(db):
    from django.contrib.auth.models import Group

    from tests.conftest import make_user

    user = make_user("ada-admin", "admin")
    user.refresh_from_db()
    assert user.is_staff and user.has_perm("fleet.change_robot")
    user.groups.remove(Group.objects.get(name="admin"))
    user.refresh_from_db()
    assert not user.is_staff


@pytest.mark.parametrize("value", ["false", "0", "[]", '"none"', '"ACTIVE"', "{}"])
def test_a_desired_state_that_is_not_a_state_is_refused_and_nothing_changes(operator_client, node, value):
    node.desired_state = "active"
    node.save()
    response = operator_client.put(f"/api/v1/nodes/{node.key}/desired-state", '{"desired_state": %s}' % value,
                                   content_type="application/json")
    assert response.status_code == 400 and error_code(response) == "invalid_field"
    node.refresh_from_db()
    assert node.desired_state == "active"
    response = operator_client.put(f"/api/v1/nodes/{node.key}/desired-state", '{"desired_state": null}',
                                   content_type="application/json")
    assert response.status_code == 200 and response.json()["desired_state"] is None


def test_runs_of_an_unknown_robot_are_404_and_of_a_known_one_a_list(operator_client, node):
    response = operator_client.get("/api/v1/robots/ghost/runs")
    assert response.status_code == 404 and error_code(response) == "not_found" and "ghost" in response.json()[
        "error"]["message"]
    assert operator_client.get(f"/api/v1/robots/{node.robot.name}/runs").json() == {"runs": []}
