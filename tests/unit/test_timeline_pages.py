"""The timeline pages and API endpoints: who may see them, what they show, the window chooser,
the links to them, and a fixed number of queries however many records the window holds."""
from __future__ import annotations

import re
from datetime import timedelta

import pytest
from django.utils import timezone

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import ManagedNode, Robot
from ros_gateway.shared import state_machine as sm
from tests.conftest import client_of


def record(node: ManagedNode, minutes_ago: float, start: int, result: int | None, outcome: str = "succeeded"):
    at = timezone.now() - timedelta(minutes=minutes_ago)
    TransitionRecord.objects.create(
        node=node, robot=node.robot, robot_name=node.robot.name, node_name=node.name, start_state_id=start,
        result_state_id=result, outcome=outcome, source="api", requested_at=at, completed_at=at, duration_ms=0.0,
    )


@pytest.fixture
def nodes(db) -> tuple[ManagedNode, ManagedNode]:
    robot = Robot.objects.create(name="tl-page-agv", domain_id=63)
    long_ago = timezone.now() - timedelta(days=30)
    lidar = ManagedNode.objects.create(robot=robot, name="/lidar_driver", alive=True, state_id=sm.ACTIVE,
                                       state_label="active", first_seen=long_ago, last_seen=timezone.now(),
                                       state_changed=timezone.now() - timedelta(minutes=30), desired_state="active")
    camera = ManagedNode.objects.create(robot=robot, name="/camera_driver", alive=True, state_id=sm.INACTIVE,
                                        state_label="inactive", first_seen=long_ago, last_seen=timezone.now(),
                                        state_changed=long_ago)
    record(lidar, 180, sm.UNCONFIGURED, sm.INACTIVE)
    record(lidar, 30, sm.INACTIVE, sm.ACTIVE)
    record(lidar, 20, sm.ACTIVE, sm.ACTIVE, "failed")
    return lidar, camera


def test_node_timeline_page_draws_the_states_and_figures(viewer_client, nodes, django_assert_max_num_queries):
    lidar, _ = nodes
    # + the marked records' reasons, the gateway's outages, the diagnostic statuses it reports (and
    # their level changes in the window: one query however many)
    with django_assert_max_num_queries(14):
        response = viewer_client.get(f"/nodes/{lidar.key}/timeline/?window=hour")
    assert response.status_code == 200
    page = response.content.decode()
    assert "<svg" in page and 'id="tl-active"' in page and 'id="tl-inactive"' in page
    # Each bar is filled with its state's pattern and names it where it fits: readable in greyscale.
    assert re.search(r'data-state="inactive".*fill="url\(#tl-inactive\)".*>inactive</text>', page)
    assert re.search(r'data-state="active".*fill="url\(#tl-active\)".*>active</text>', page)
    assert re.search(r"<strong>50\.\d\d %</strong> in active", page)  # 30 of 60 minutes
    assert "<dt>Failures</dt><dd>1</dd>" in page
    assert 'aria-current="page">hour</a>' in page and 'href="?window=week"' in page
    assert "UTC" in page and 'class="tl-time"' in page
    assert "style=" not in page.split("<main", 1)[1]  # the CSP allows no inline style


def test_window_chooser_refuses_unknown_windows_readably(viewer_client, nodes):
    response = viewer_client.get(f"/nodes/{nodes[0].key}/timeline/?window=year")
    page = response.content.decode()
    assert response.status_code == 200
    assert "There is no window &#x27;year&#x27; (there are 15min, hour, day, week). Showing the last day." in page
    assert 'aria-current="page">day</a>' in page


def test_robot_timeline_page_lists_each_node(viewer_client, nodes, django_assert_max_num_queries):
    lidar, camera = nodes
    with django_assert_max_num_queries(12):  # + the marked records' reasons, the gateway's outages
        response = viewer_client.get(f"/robots/{lidar.robot.name}/timeline/?window=day")
    assert response.status_code == 200
    page = response.content.decode()
    assert f'href="/nodes/{lidar.key}/timeline/?window=day"' in page
    assert f'href="/nodes/{camera.key}/timeline/?window=day"' in page
    assert 'class="tl-name" x="0"' in page and ">/camera_driver</text>" in page
    assert "no desired state set" in page  # the camera has none


def test_timeline_pages_need_a_role_and_an_existing_node(client, db, nodes):
    no_role = client_of("nora-norole", None)
    assert no_role.get(f"/nodes/{nodes[0].key}/timeline/").status_code == 403
    assert client.get(f"/nodes/{nodes[0].key}/timeline/").status_code == 302  # to the login page
    viewer = client_of("vera-viewer", "viewer")
    assert viewer.get("/nodes/tl-page-agv.nothing/timeline/").status_code == 404
    assert viewer.get("/robots/no-such-robot/timeline/").status_code == 404


def test_node_and_fleet_pages_link_to_the_timelines(viewer_client, nodes):
    lidar, _ = nodes
    assert f'href="/nodes/{lidar.key}/timeline/"' in viewer_client.get(f"/nodes/{lidar.key}/").content.decode()
    assert f'href="/robots/{lidar.robot.name}/timeline/"' in viewer_client.get("/").content.decode()


def test_api_node_timeline(viewer_client, nodes):
    lidar, camera = nodes
    body = viewer_client.get(f"/api/v1/nodes/{lidar.key}/timeline?window=hour").json()
    assert body["node"] == lidar.key and body["window"]["name"] == "hour"
    assert body["desired_state"] == "active" and body["availability_percent"] == pytest.approx(50, abs=0.1)
    assert body["failures"] == 1 and body["restarts"] == 0 and body["outcomes"] == {"succeeded": 1, "failed": 1}
    assert [s["state"] for s in body["segments"]] == ["inactive", "active"]
    assert body["segments"][0]["from_s"] == 0 and body["segments"][-1]["to_s"] == 3600
    assert body["segments"][0]["to_s"] == body["segments"][1]["from_s"] == pytest.approx(1800, abs=5)
    assert {row["state"] for row in body["time_in_state"]} == {"inactive", "active"}
    assert body["not_read_before"] is None and body["records_read"] == 2
    other = viewer_client.get(f"/api/v1/nodes/{camera.key}/timeline").json()
    assert other["window"]["name"] == "day" and other["availability_percent"] is None


def test_api_robot_timeline_and_its_errors(viewer_client, nodes, client):
    robot = nodes[0].robot.name
    body = viewer_client.get(f"/api/v1/robots/{robot}/timeline?window=week").json()
    assert body["robot"] == robot and len(body["nodes"]) == 2 and body["failures"] == 1
    refused = viewer_client.get(f"/api/v1/robots/{robot}/timeline?window=month")
    assert refused.status_code == 400 and refused.json()["error"]["code"] == "invalid_field"
    assert "hour, day, week" in refused.json()["error"]["message"]
    missing = viewer_client.get("/api/v1/robots/nobody/timeline")
    assert missing.status_code == 404 and missing.json()["error"]["code"] == "not_found"
    assert viewer_client.get("/api/v1/nodes/nobody.none/timeline").status_code == 404
    assert client.get(f"/api/v1/robots/{robot}/timeline").status_code == 401
