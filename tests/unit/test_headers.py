"""Security headers of the site's answers."""
from __future__ import annotations

from django.test import Client

from lifecycle_site.fleet.models import ManagedNode, Robot
from ros_gateway.shared import state_machine as sm


def test_pages_and_api_answers_are_not_stored_by_browsers(viewer_client):
    robot = Robot.objects.create(name="hdr-agv", domain_id=99)
    node = ManagedNode.objects.create(robot=robot, name="/lidar", alive=True, state_id=sm.UNCONFIGURED,
                                      state_label="unconfigured")
    for path in ("/", "/api/v1/nodes", f"/nodes/{node.key}/", "/audit/", "/login/"):
        header = viewer_client.get(path)["Cache-Control"]
        assert "no-store" in header and "private" in header, (path, header)
    assert "no-store" in Client().get("/api/v1/nodes")["Cache-Control"]  # the 401 too
