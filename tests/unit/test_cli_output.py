"""What the CLI prints (operations/cli_output.py): the diagnostics lines (a status per line,
indented by depth, its message, node and age; a robot whose statuses are all OK says so under
--problems) and a run's summary line (a mode's names the mode)."""
from __future__ import annotations

from datetime import datetime, timedelta, timezone

from lifecycle_site.fleet.models import GroupRun, Robot
from lifecycle_site.operations.cli_output import diagnostic_lines, summary_line

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


def test_a_runs_summary_names_its_operation_or_its_mode(db):
    robot = Robot(name="agv-1")
    bringup = GroupRun(robot=robot, operation="bringup", status="succeeded", message="2 succeeded")
    assert summary_line(bringup) == "bringup agv-1: succeeded (2 succeeded)"
    mode = GroupRun(robot=robot, operation="mode", plan={"mode": "mapping"}, status="succeeded",
                    message="3 succeeded, 1 skipped")
    assert summary_line(mode) == "mode mapping on agv-1: succeeded (3 succeeded, 1 skipped)"
