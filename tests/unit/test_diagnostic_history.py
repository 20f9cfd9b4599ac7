"""A status's level over a window (lifecycle_site/diagnostics/history.py): opened by the change
before it, one segment per level, and a node's lanes in two queries however many statuses; the
tree by name path with each branch showing the worst below it (diagnostics/tree.py); stale
statuses forgotten by an operator only."""
from __future__ import annotations

from datetime import datetime, timedelta, timezone

import pytest

from lifecycle_site.diagnostics import history, tree
from lifecycle_site.diagnostics.models import ERROR, OK, STALE, WARN, LevelChange, Status
from lifecycle_site.fleet.models import Gateway, Robot

START = datetime(2026, 11, 27, 10, 0, tzinfo=timezone.utc)
END = START + timedelta(hours=1)


@pytest.fixture
def robot(db) -> Robot:
    return Robot.objects.create(name="hist", domain_id=3, gateway=Gateway.objects.create(name="gw-hist"))


def status(robot: Robot, name: str, level: int = OK, node: str = "/driver", **fields) -> Status:
    return Status.objects.create(robot=robot, name=name, level=level, node=node, heard=END, level_since=START,
                                 **fields)


def change(robot: Robot, name: str, minutes: float, level: int, message: str = "") -> None:
    LevelChange.objects.create(robot=robot, name=name, level=level, message=message,
                               at=START + timedelta(minutes=minutes))


def test_a_lane_opens_with_the_level_before_the_window(robot):
    status(robot, "driver: link", ERROR)
    change(robot, "driver: link", -30, WARN, "slow")
    change(robot, "driver: link", 15, ERROR, "lost")
    change(robot, "driver: link", 45, STALE, "lost")
    segments = history.lane(robot, "driver: link", START, END)
    assert [(s.word, s.left, s.width) for s in segments] == [("WARN", 0.0, 25.0), ("ERROR", 25.0, 50.0),
                                                            ("STALE", 75.0, 25.0)]
    assert segments[0].message == "slow"


def test_a_nodes_lanes_take_two_queries_however_many_statuses(robot, django_assert_num_queries):
    for index in range(5):
        status(robot, f"driver: check {index}")
        change(robot, f"driver: check {index}", -5, OK)
        change(robot, f"driver: check {index}", 30, WARN)
    status(robot, "other: x", node="/other")
    with django_assert_num_queries(2):
        lanes = history.node_lanes(robot, "/driver", START, END)
    assert [lane["name"] for lane in lanes] == [f"driver: check {i}" for i in range(5)]
    assert [(s.word, s.width) for s in lanes[0]["segments"]] == [("OK", 50.0), ("WARN", 50.0)]


def test_the_tree_sums_up_the_worst_below(robot):
    status(robot, "/R")
    status(robot, "/R/Sensors")
    status(robot, "/R/Sensors/Lidar", WARN)
    status(robot, "/R/Sensors/Camera", stale=True)
    status(robot, "/R/Power/Battery", ERROR)  # "/R/Power" itself is not reported
    status(robot, "joystick: link")
    rows = tree.rows(tree.build(Status.objects.filter(robot=robot)))
    found = {row.path: (row.depth, row.word, row.status is not None) for row in rows}
    assert found == {"/R": (0, "ERROR", True), "/R/Power": (1, "ERROR", False), "/R/Power/Battery": (2, "ERROR", True),
                     "/R/Sensors": (1, "STALE", True), "/R/Sensors/Camera": (2, "STALE", True),
                     "/R/Sensors/Lidar": (2, "WARN", True), "joystick: link": (0, "OK", True)}
    assert [row.path for row in rows][:4] == ["joystick: link", "/R", "/R/Power", "/R/Power/Battery"]  # by name


def test_an_operator_forgets_stale_statuses_a_viewer_may_not(robot, operator_client, viewer_client):
    status(robot, "gone: driver", stale=True)
    change(robot, "gone: driver", 1, STALE)
    status(robot, "alive: driver")
    url = f"/robots/{robot.name}/diagnostics/forget-stale"
    assert viewer_client.post(url).status_code == 403
    assert Status.objects.filter(robot=robot).count() == 2
    answer = operator_client.post(url)
    assert answer.status_code == 200 and "Forgot 1 stale status: gone: driver" in answer.content.decode()
    assert list(Status.objects.filter(robot=robot).values_list("name", flat=True)) == ["alive: driver"]
    assert not LevelChange.objects.filter(robot=robot, name="gone: driver").exists()
    assert operator_client.get(url).status_code == 405


def test_the_forget_button_shows_for_an_operator_while_a_status_is_stale(robot, operator_client, viewer_client):
    page = f"/robots/{robot.name}/diagnostics/"
    status(robot, "alive: driver")
    assert "Forget" not in operator_client.get(page).content.decode()
    status(robot, "gone: driver", stale=True)
    status(robot, "gone: camera", stale=True)
    status(robot, "reported stale: imu", STALE)  # a node's own STALE level is not forgotten
    assert "Forget 2 stale statuses" in operator_client.get(page).content.decode()
    assert "Forget" not in viewer_client.get(page).content.decode()
