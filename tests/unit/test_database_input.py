"""Values the database cannot take (PostgreSQL refuses a NUL character in text and text
longer than its column, where SQLite stores them) are the client's error: 400 or 404, never
500, on the pages and in the API. `make test-postgres` runs this module on PostgreSQL."""
from __future__ import annotations

import pytest

from lifecycle_site.audit.models import AccessDenial
from lifecycle_site.fleet.models import ManagedNode, Robot


@pytest.fixture
def robot(db) -> Robot:
    return Robot.objects.create(name="input-agv", domain_id=98)


@pytest.mark.parametrize("path", ["/api/v1/nodes/%00", "/api/v1/nodes/%00/parameters", "/api/v1/robots/%00/runs",
                                  "/nodes/%00/", "/logs/robot/%00/"])
def test_a_nul_character_in_a_path_is_not_a_server_error(operator_client, robot, path):
    response = operator_client.get(path)
    assert response.status_code in (400, 404), (path, response.status_code, response.content[:300])
    if path.startswith("/api/"):
        assert response.json()["error"]["code"] in ("bad_request", "not_found")


def test_a_nul_character_in_a_command_is_refused_in_the_apis_json(operator_client, robot):
    response = operator_client.post("/api/v1/nodes/%00/transition", '{"transition": "configure"}',
                                    content_type="application/json")
    assert response.status_code in (400, 404), response.content[:300]
    assert response.json()["error"]["code"] in ("bad_request", "not_found")


def test_a_node_name_longer_than_its_column_is_not_a_server_error(operator_client, robot):
    name = "/" + "x" * 300
    response = operator_client.post(f"/robots/{robot.name}/watch", {"name": name})
    # The watch form refuses it as not a node name (on SQLite too, which would store it).
    assert response.status_code in (302, 400), response.content[:300]
    assert not ManagedNode.objects.filter(robot=robot).exists()


def test_a_refusal_with_a_nul_character_is_still_on_record(client, robot):
    response = client.post("/api/v1/nodes/agv%00/transition", '{"transition": "configure"}',
                           content_type="application/json", HTTP_AUTHORIZATION="Bearer bad\x00token")
    assert response.status_code == 401, response.content[:300]
    denial = AccessDenial.objects.get()
    assert denial.path == "/api/v1/nodes/agv\ufffd/transition" and denial.code == "bad_token"
