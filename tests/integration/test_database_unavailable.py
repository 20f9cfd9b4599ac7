"""A database that does not answer gets the API's JSON error (503, what to do), not Django's HTML
500, whether the token check or the view meets it; once it answers again, the same request works.

Held for real: another connection takes the write lock (SQLite; locked past the site's timeout)
or locks the tables (PostgreSQL, ``make test-postgres``), and the site's connection gives up
after half a second instead of its 20 s."""
from __future__ import annotations

from contextlib import contextmanager
from typing import Iterator

import pytest
from django.db import connection
from django.test import Client

from lifecycle_site.api.models import ApiToken
from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import Gateway, ManagedNode, Robot
from tests.conftest import make_user
from tests.integration.conftest import register, transition

ROBOT, GATEWAY = "db-agv", "cell-db"
LOCKED_TABLES = ("api_apitoken", "fleet_managednode", "audit_transitionrecord")


@contextmanager
def database_held() -> Iterator[None]:
    """The site's database busy with another connection's lock until the block ends."""
    holder = connection.get_new_connection(connection.get_connection_params())  # a second one, as Django opens it
    options = connection.settings_dict.setdefault("OPTIONS", {})
    saved = dict(options)
    if connection.vendor == "sqlite":
        options["timeout"] = 0.5
        holder.execute("BEGIN IMMEDIATE")  # the write lock: every writer waits for it
    else:
        options["options"] = "-c lock_timeout=500"
        holder.execute(f"LOCK TABLE {', '.join(LOCKED_TABLES)} IN ACCESS EXCLUSIVE MODE")
    connection.close()  # the next query connects with the short timeout
    try:
        yield
    finally:
        holder.rollback()
        holder.close()
        options.clear()
        options.update(saved)
        connection.close()


@pytest.fixture
def offline_robot(live_db, redis_server):
    register(ROBOT, 0, gateway=GATEWAY)  # its gateway never started: commands are refused, on record
    ManagedNode.objects.get_or_create(robot=Robot.objects.get(name=ROBOT), name="/lidar_driver",
                                      defaults={"alive": True})
    yield f"{ROBOT}.lidar_driver"
    Robot.objects.filter(name=ROBOT).delete()
    Gateway.objects.filter(name=GATEWAY).delete()


def test_a_command_while_the_database_does_not_answer_gets_a_json_503(api, offline_robot):
    before = TransitionRecord.objects.filter(robot_name=ROBOT).count()
    with database_held():
        response = transition(api, offline_robot, "configure")
    assert response.status_code == 503, response.content[:200]
    error = response.json()["error"]
    assert error["code"] == "database_unavailable", error
    assert "did not answer" in error["message"] and "look at the node" in error["message"], error
    # Answered again once the database is back: refused (its gateway is offline), on record.
    response = transition(api, offline_robot, "configure")
    assert response.json()["error"]["code"] == "gateway_offline", response.json()
    assert TransitionRecord.objects.filter(robot_name=ROBOT).count() == before + 1


def test_a_token_check_while_the_database_does_not_answer_gets_a_json_503(live_db):
    record, token = ApiToken.issue(make_user("dora-viewer", "viewer"), "db test")
    client = Client(headers={"Authorization": f"Bearer {token}"})
    try:
        with database_held():  # a token not used yet: its first use is written down
            response = client.get("/api/v1/nodes")
        assert response.status_code == 503, response.content[:200]
        assert response.json()["error"]["code"] == "database_unavailable"
        assert client.get("/api/v1/nodes").status_code == 200
    finally:
        record.delete()
