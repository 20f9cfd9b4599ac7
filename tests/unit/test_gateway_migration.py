"""Upgrading a site with robots: every robot ends up on the gateway ``local`` (the one on the
site's machine, as before), and the migration can be undone."""
from __future__ import annotations

import pytest
from django.db import connection
from django.db.migrations.executor import MigrationExecutor

BEFORE = [("fleet", "0003_order_help")]


def migrate(targets) -> MigrationExecutor:
    executor = MigrationExecutor(connection)
    executor.migrate(targets)
    return MigrationExecutor(connection)


@pytest.mark.django_db(transaction=True)
def test_existing_robots_go_to_the_gateway_local_and_back():
    latest = MigrationExecutor(connection).loader.graph.leaf_nodes()
    try:
        executor = migrate(BEFORE)
        old = executor.loader.project_state(BEFORE).apps
        for name, domain in (("old-agv-1", 11), ("old-agv-2", 12)):
            old.get_model("fleet", "Robot").objects.create(name=name, domain_id=domain)

        executor = migrate(latest)
        new = executor.loader.project_state(latest).apps
        robots = new.get_model("fleet", "Robot").objects.order_by("name")
        assert [(r.name, r.gateway.name) for r in robots] == [("old-agv-1", "local"), ("old-agv-2", "local")]
        assert list(new.get_model("fleet", "Gateway").objects.values_list("name", flat=True)) == ["local"]

        executor = migrate(BEFORE)  # and back: the robots stay, without a gateway
        old = executor.loader.project_state(BEFORE).apps
        assert sorted(old.get_model("fleet", "Robot").objects.values_list("name", flat=True)) == [
            "old-agv-1", "old-agv-2"]
    finally:
        migrate(latest)

    from lifecycle_site.fleet.models import Robot

    assert Robot.objects.get(name="old-agv-1").gateway.name == "local"
