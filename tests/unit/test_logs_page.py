"""The log console's filters on the server: they come from the page's address, the download
applies the plain ones (text, not, nodes to keep or hide) and never runs a regular expression."""
from __future__ import annotations

from datetime import datetime, timezone

import pytest

from lifecycle_site.fleet.models import LogRecord, ManagedNode, Robot

LINES = [
    ("lidar_driver", 20, "scan ok"),
    ("lidar_driver", 30, "scan late by 40 ms"),
    ("camera_driver", 30, "frame late"),
    ("planner", 40, "no path to goal"),
    ("agv9.camera_driver", 20, "frame ok"),
]


@pytest.fixture
def robot(db):
    robot = Robot.objects.create(name="logs-agv", domain_id=98)
    node = ManagedNode.objects.create(robot=robot, name="/lidar_driver", key="logs-agv.lidar_driver")
    for logger, level, message in LINES:
        LogRecord.objects.create(robot=robot, node=node if logger == "lidar_driver" else None, logger=logger,
                                 level=level, message=message,
                                 stamp=datetime(2026, 11, 23, 14, 5, 6, 789000, tzinfo=timezone.utc))
    return robot


def download(client, **query) -> list[str]:
    text = client.get("/logs/robot/logs-agv/download", query).content.decode()
    return [line for line in text.splitlines() if not line.startswith("#")]


def test_the_download_applies_text_not_and_node_filters(viewer_client, robot):
    assert len(download(viewer_client)) == 5
    assert [line.split("] ", 2)[-1] for line in download(viewer_client, q="late")] == [
        "scan late by 40 ms", "frame late"]
    assert len(download(viewer_client, **{"not": "late"})) == 3
    assert [line.split("] ", 2)[-1] for line in download(viewer_client, node="lidar, planner")] == [
        "scan ok", "scan late by 40 ms", "no path to goal"]
    assert len(download(viewer_client, xnode="camera")) == 3
    assert download(viewer_client, level="WARN", xnode="camera_driver", q="scan") == [
        "2026-11-23 14:05:06.789000 UTC [WARN] [lidar_driver] scan late by 40 ms"]


def test_a_regular_expression_is_never_run_on_the_server(viewer_client, robot):
    # A pattern that backtracks exponentially: with re=1 the server applies the level only.
    evil = "(a+)+$"
    assert len(download(viewer_client, q=evil, re="1")) == 5
    body = viewer_client.get("/logs/robot/logs-agv/download", {"q": evil, "re": "1", "level": "WARN",
                                                                "format": "json"}).json()
    assert [r["message"] for r in body["records"]] == ["scan late by 40 ms", "frame late", "no path to goal"]
    assert body["title"] == "logs-agv (all nodes)"


def test_the_page_takes_its_filters_from_its_address(viewer_client, robot):
    query = {"level": "warn", "q": "late", "not": "frame", "node": "lidar", "xnode": "x" * 500, "re": "1"}
    page = viewer_client.get("/logs/robot/logs-agv/", query).content.decode()
    assert '<option value="WARN" selected>' in page
    assert 'name="q" value="late"' in page and 'name="not" value="frame"' in page
    assert 'name="node" value="lidar"' in page
    assert f'name="xnode" value="{"x" * 200}"' in page  # bounded
    assert 'name="re" value="1" checked' in page
    assert '<option value="lidar_driver">' in page  # node names offered
    assert "Times in UTC" in page
    node_page = viewer_client.get("/logs/node/logs-agv.lidar_driver/").content.decode()
    assert 'name="node"' not in node_page  # one node: nothing to choose
