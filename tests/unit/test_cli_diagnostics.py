"""The CLI's diagnostics lines (operations/cli_output.py): a status per line, indented by depth,
its message, node and age; a robot whose statuses are all OK says so under --problems."""
from __future__ import annotations

from datetime import datetime, timedelta, timezone

from lifecycle_site.operations.cli_output import diagnostic_lines

NOW = datetime(2026, 11, 27, 9, 0, tzinfo=timezone.utc)


def test_lines_are_indented_with_message_node_and_age():
    heard = (NOW - timedelta(seconds=4)).isoformat()
    rows = [{"depth": 0, "shown": "ERROR", "label": "Robot", "status": None},
            {"depth": 1, "shown": "ERROR", "label": "Lidar",
             "status": {"message": "no scans", "node": "/lidar_driver", "heard": heard}}]
    assert diagnostic_lines(rows, "agv-2", NOW, 2) == [
        "ERROR  Robot", "  ERROR  Lidar: no scans (/lidar_driver, 4 s ago)"]


def test_nothing_to_list_says_why():
    assert diagnostic_lines([], "agv-1", NOW, 0) == ["No diagnostics heard from agv-1 yet."]
    assert diagnostic_lines([], "agv-1", NOW, 3) == ["Every diagnostic status of agv-1 is OK (3)."]
