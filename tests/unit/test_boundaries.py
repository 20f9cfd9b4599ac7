"""Boundaries. Of the code: dependencies run one way (the gateway never imports the site, the
site imports only the shared vocabulary of the gateway, and the vocabulary imports neither rclpy
nor Django). Of the API's input: whatever a request holds, the answer is a 4xx in the API's JSON
error shape, never a 500, within the limits of docs/api.md ("Limits"); nothing is sent to a
robot or written to the audit log for what is refused. (The HTTP layer's limits, under daphne:
tests/integration/test_fuzz.py.)"""
from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from django.test import Client

from lifecycle_site.api import limits
from lifecycle_site.audit.models import ParameterRecord, TransitionRecord
from lifecycle_site.fleet.models import GroupRun, ManagedNode, Robot
from ros_gateway.shared import state_machine as sm

ROOT = Path(__file__).resolve().parents[2]


def imports(path: Path) -> set[str]:
    """Every module a file imports (absolute names; relative imports are not used here)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names)
    return found


def sources(folder: str) -> list[Path]:
    return sorted((ROOT / folder).rglob("*.py"))


def test_nothing_under_ros_gateway_imports_the_site():
    offenders = {
        str(path.relative_to(ROOT)): sorted(name for name in imports(path) if name.startswith("lifecycle_site"))
        for path in sources("ros_gateway")
    }
    assert {path: names for path, names in offenders.items() if names} == {}


def test_the_gateway_never_reaches_the_site_settings_included():
    """No Django at all under ros_gateway (a management command or an app config there would run
    the gateway on the site's settings), and the gateway starts and reads its settings without
    them: with DJANGO_SETTINGS_MODULE unset, nothing of lifecycle_site or django is loaded."""
    offenders = {
        str(path.relative_to(ROOT)): sorted(n for n in imports(path) if n.split(".")[0] in ("django", "lifecycle_site"))
        for path in sources("ros_gateway")
    }
    assert {path: names for path, names in offenders.items() if names} == {}
    assert not (ROOT / "ros_gateway" / "management").exists() and not (ROOT / "ros_gateway" / "apps.py").exists()
    probe = (
        "import sys\n"
        "from ros_gateway.__main__ import arguments\n"
        "from ros_gateway.config import GatewayConfig\n"
        "from ros_gateway import service, groups, commands\n"
        "GatewayConfig.load(arguments(['--name', 'cell-a']).name, {'REDIS_URL': 'redis://127.0.0.1:1/0'})\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('django', 'lifecycle_site')))\n"
    )
    environ = {k: v for k, v in os.environ.items() if k != "DJANGO_SETTINGS_MODULE"}
    done = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, env=environ, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]", done.stdout


def test_the_gateway_uses_no_database():
    database = ("django.db", "django.contrib.auth", "asgiref.sync")
    offenders = {
        str(path.relative_to(ROOT)): sorted(n for n in imports(path) if n.startswith(database))
        for path in sources("ros_gateway")
    }
    assert {path: names for path, names in offenders.items() if names} == {}


def test_the_site_imports_only_the_shared_vocabulary_of_the_gateway():
    offenders = {}
    for path in sources("lifecycle_site"):
        names = sorted(
            name for name in imports(path)
            if name.startswith("ros_gateway") and not name.startswith("ros_gateway.shared")
        )
        if names:
            offenders[str(path.relative_to(ROOT))] = names
    assert offenders == {}


def test_the_shared_vocabulary_needs_neither_rclpy_nor_django():
    for path in sources("ros_gateway/shared"):
        heavy = sorted(n for n in imports(path) if n.split(".")[0] in ("rclpy", "django", "channels", "redis"))
        assert heavy == [], f"{path.name} imports {heavy}"


# --- the API's input -----------------------------------------------------------------------------
@pytest.fixture
def node(db) -> ManagedNode:
    robot = Robot.objects.create(name="edge-agv", domain_id=98)
    return ManagedNode.objects.create(
        robot=robot, name="/joy_to_vel", alive=True, state_id=sm.UNCONFIGURED, state_label="unconfigured"
    )


def send(client: Client, method: str, path: str, body: str | bytes):
    return getattr(client, method)(path, body, content_type="application/json")


def refusal(response, status: int, code: str) -> str:
    """The message of a refusal in the API's error shape (asserting status and code)."""
    assert response.status_code == status, response.content[:300]
    assert response["Content-Type"] == "application/json", response.content[:300]
    error = response.json()["error"]
    assert error["code"] == code, error
    return error["message"]


@pytest.mark.parametrize("depth", [40, 5_000, 100_000])
def test_deeply_nested_bodies_are_refused_not_a_500(operator_client, node, depth):
    # 100,000 "[" made json.loads raise RecursionError: a 500 HTML page.
    for method, path in (("post", f"/api/v1/nodes/{node.key}/transition"),
                         ("patch", f"/api/v1/nodes/{node.key}/parameters"),
                         ("put", f"/api/v1/nodes/{node.key}/desired-state")):
        for body in ("[" * depth + "]" * depth, "[" * depth if depth > 2000 else "[" * depth + "]" * depth):
            message = refusal(send(operator_client, method, path, body), 400, "too_deep")
            assert f"deeper than {limits.MAX_DEPTH} levels" in message
    nested = '{"transition": "configure", "x": ' + "[" * depth + "]" * depth + "}"
    refusal(send(operator_client, "post", f"/api/v1/nodes/{node.key}/transition", nested), 400, "too_deep")
    assert not TransitionRecord.objects.exists()


def test_nesting_up_to_the_limit_is_parsed(operator_client, node):
    body = '{"transition": "launch", "x": ' + "[" * (limits.MAX_DEPTH - 1) + "]" * (limits.MAX_DEPTH - 1) + "}"
    refusal(send(operator_client, "post", f"/api/v1/nodes/{node.key}/transition", body), 400, "unknown_transition")


@pytest.mark.parametrize("label", ["²", "³", "١", "٣", "𝟑", "1" * 5000, "99999999999", "-1"])
def test_unicode_and_overlong_digit_strings_are_unknown_transitions(operator_client, node, label):
    # "²".isdigit() is True but int("²") fails: that was a 500; "1" * 5000 exceeds int()'s limit.
    response = send(operator_client, "post", f"/api/v1/nodes/{node.key}/transition", json.dumps({"transition": label}))
    message = refusal(response, 400, "unknown_transition")
    assert len(message) < 300
    assert not TransitionRecord.objects.exists()


def test_resolve_transition_takes_only_ascii_digits():
    assert sm.resolve_transition(" 3 ", sm.INACTIVE).label == "activate"
    for text in ("²", "١", "٣", "𝟑", "1" * 5000):
        with pytest.raises(sm.UnknownTransition):
            sm.resolve_transition(text, sm.INACTIVE)


def test_a_body_over_the_limit_is_413_in_json(operator_client, node, settings):
    assert settings.DATA_UPLOAD_MAX_MEMORY_SIZE == limits.body_limit() == 1024 * 1024
    big = json.dumps({"transition": "configure", "pad": "x" * (limits.body_limit() + 1)})
    for method, path in (("post", f"/api/v1/nodes/{node.key}/transition"),
                         ("patch", f"/api/v1/nodes/{node.key}/parameters"),
                         ("post", f"/api/v1/robots/{node.robot.name}/operations")):
        message = refusal(send(operator_client, method, path, big), 413, "body_too_large")
        assert "larger than 1 MiB" in message
    assert not TransitionRecord.objects.exists() and not GroupRun.objects.exists()


def test_writes_to_an_unknown_api_path_are_404_not_a_csrf_page(db, node):
    from tests.conftest import make_user

    browser = Client(enforce_csrf_checks=True)  # a session, no CSRF token: only known paths check it
    browser.force_login(make_user("uma-operator", "operator"))
    for method in ("post", "put", "patch", "delete"):
        response = getattr(browser, method)("/api/v1/nope", "{}", content_type="application/json")
        message = refusal(response, 404, "not_found")
        assert "/api/v1/nope" in message
    assert refusal(Client().post("/api/v1/" + "x" * 10_000), 404, "not_found").endswith("see docs/api.md.")


def test_too_many_parameters_are_refused_before_anything_is_sent(operator_client, node):
    # 10,000 unknown names were each sent, and each written to the audit log (6 s).
    names = {f"p{i}": 1 for i in range(limits.MAX_PARAMETERS + 1)}
    message = refusal(send(operator_client, "patch", f"/api/v1/nodes/{node.key}/parameters", json.dumps(names)),
                      400, "too_many_items")
    assert f"{limits.MAX_PARAMETERS + 1} parameters" in message and f"at most {limits.MAX_PARAMETERS}" in message
    assert not ParameterRecord.objects.exists()


def test_group_operations_take_a_bounded_list_of_nodes(operator_client, node):
    path = f"/api/v1/robots/{node.robot.name}/operations"
    many = json.dumps({"operation": "bringup", "nodes": [f"/n{i}" for i in range(limits.MAX_NODES + 1)]})
    refusal(send(operator_client, "post", path, many), 400, "too_many_items")
    long_name = json.dumps({"operation": "bringup", "nodes": ["/" + "n" * 300]})
    refusal(send(operator_client, "post", path, long_name), 400, "invalid_field")
    huge = json.dumps({"operation": "x" * 100_000})
    assert len(refusal(send(operator_client, "post", path, huge), 400, "unknown_operation")) < 300
    assert not GroupRun.objects.exists()


def test_overlong_numbers_are_refused_plainly(operator_client, node):
    path = f"/api/v1/nodes/{node.key}/transition"
    digits = '{"transition": "configure", "timeout": ' + "9" * 5000 + "}"
    message = refusal(send(operator_client, "post", path, digits), 400, "malformed_json")
    assert "a number has 5,000 digits; at most 4,300 are accepted" in message
    assert "set_int_max_str_digits" not in message
    for timeout in ("1e308", "1" + "0" * 400, "-1e308", "1e-400"):
        body = '{"transition": "configure", "timeout": ' + timeout + "}"
        refusal(send(operator_client, "post", path, body), 400, "invalid_field")
    refusal(send(operator_client, "post", path, '{"transition": 1e999}'), 400, "non_finite_number")
    assert not TransitionRecord.objects.exists()


def test_ids_and_queries_of_any_length_are_json_answers(operator_client, node):
    long_id = "x" * 16_000
    message = refusal(operator_client.get(f"/api/v1/nodes/{long_id}"), 404, "not_found")
    assert len(message) < 300
    refusal(operator_client.get(f"/api/v1/nodes?robot={long_id}"), 404, "not_found")
    refusal(operator_client.get(f"/api/v1/runs/{long_id}"), 404, "not_found")
    fields = "&".join(f"f{i}=1" for i in range(1500))  # over DATA_UPLOAD_MAX_NUMBER_FIELDS
    for path in ("/api/v1/transitions", f"/api/v1/nodes/{node.key}/logs", "/api/v1/nodes"):
        refusal(operator_client.get(f"{path}?{fields}"), 400, "too_many_fields")


def test_a_body_that_is_not_utf8_is_named_so(operator_client, node):
    body = b'{"transition": "\xff"}'
    response = send(operator_client, "post", f"/api/v1/nodes/{node.key}/transition", body)
    message = refusal(response, 400, "malformed_json")
    assert message.startswith("The request body is not UTF-8 text")


def test_refusals_before_any_view_can_answer_in_json():
    # For handler400 (lifecycle_site/urls.py): Django's HTML page answered a Host header not in
    # ALLOWED_HOSTS, even under /api/.
    from django.core.exceptions import DisallowedHost
    from django.test import RequestFactory

    from lifecycle_site.api.auth import bad_request

    api = bad_request(RequestFactory().get("/api/v1/robots"), DisallowedHost("Invalid HTTP_HOST header: 'x'"))
    assert api.status_code == 400 and api["Content-Type"] == "application/json"
    assert json.loads(api.content)["error"]["code"] == "bad_request"
    assert "Invalid HTTP_HOST header" in json.loads(api.content)["error"]["message"]
    page = bad_request(RequestFactory().get("/audit/"), DisallowedHost("x"))
    assert page.status_code == 400 and page["Content-Type"].startswith("text/html")


def test_no_two_apps_of_the_site_import_each_other():
    """Each pair of the site's apps depends one way at most (alerts watch fleet through
    ingest/watchers.py; the API's alert endpoints live in api; timelines are their own package)."""
    apps = sorted(p.name for p in (ROOT / "lifecycle_site").iterdir() if (p / "__init__.py").exists())
    uses: dict[str, set[str]] = {app: set() for app in apps}
    for app in apps:
        for path in sources(f"lifecycle_site/{app}"):
            if "migrations" in path.parts:
                continue
            for name in imports(path):
                parts = name.split(".")
                if parts[0] == "lifecycle_site" and len(parts) > 1 and parts[1] in uses and parts[1] != app:
                    uses[app].add(parts[1])
    both = sorted({tuple(sorted((a, b))) for a in apps for b in uses[a] if a in uses[b]})
    assert both == [], f"apps importing each other: {both}"


def test_no_product_file_is_over_400_lines():
    long = {str(p.relative_to(ROOT)): n for folder in ("lifecycle_site", "ros_gateway")
            for p in sources(folder) if (n := len(p.read_text().splitlines())) > 400}
    assert long == {}
