"""The real stack for integration tests: Redis, the site's ingest process, the gateway process
and robots in their own ROS domains, all on loopback (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST)."""
from __future__ import annotations

import pytest
from django.test import Client

from lifecycle_site.fleet.models import Gateway, ManagedNode, Robot
from tests import stack


def pytest_collection_modifyitems(items):
    for item in items:
        if "/integration/" in str(item.fspath):
            item.add_marker(pytest.mark.integration)


def register(name: str, domain_id: int, namespace: str = "", gateway: str = "local") -> Robot:
    """A robot watched by ``gateway`` (registered if need be, as ``manage.py add_robot`` does)."""
    owner, _ = Gateway.objects.get_or_create(name=gateway)
    robot, _ = Robot.objects.update_or_create(
        name=name, defaults={"domain_id": domain_id, "namespace": namespace, "enabled": True, "gateway": owner}
    )
    return robot


def node_state(api: Client, key: str) -> dict | None:
    response = api.get(f"/api/v1/nodes/{key}")
    return response.json() if response.status_code == 200 else None


def wait_node(api: Client, key: str, timeout: float = 20, **expect) -> dict:
    """Wait until the node is listed with the expected fields (alive=True, state='inactive')."""

    def matches():
        node = ManagedNode.objects.select_related("robot").filter(key=key).first()
        if node is None:
            return None
        if "alive" in expect and node.alive != expect["alive"]:
            return None
        if "state" in expect and node.state_label != expect["state"]:
            return None
        if "seen_since" in expect and (node.last_seen is None or node.last_seen < expect["seen_since"]):
            return None
        return node

    return stack.wait_for(matches, timeout, f"{key} with {expect}")


def transition(api: Client, key: str, name, **extra):
    return api.post(
        f"/api/v1/nodes/{key}/transition", {"transition": name, **extra}, content_type="application/json"
    )
