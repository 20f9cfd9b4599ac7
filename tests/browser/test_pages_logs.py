"""The log console in a real browser: a count of what is shown, filters in the address, dates
and time zone on every line, nodes to keep or hide, and regular expressions applied in the page."""
from __future__ import annotations

import re
from datetime import datetime, timedelta, timezone
from urllib.parse import parse_qs, urlparse

import pytest
from playwright.sync_api import Page, expect

from lifecycle_site.fleet.models import LogRecord, Robot
from tests.browser.conftest import ROBOT, logged_in_page

WAIT_MS = 20_000
LINES = [("lidar_driver", 20, "scan ok"), ("lidar_driver", 30, "scan late by 40 ms"),
         ("camera_driver", 30, "frame late"), ("planner", 40, "no path to goal"),
         ("camera_driver", 20, "frame ok")] * 3  # 15 lines


@pytest.fixture
def page(browser, site, robot, operator):
    robot_row = Robot.objects.get(name=ROBOT)
    LogRecord.objects.filter(robot=robot_row).delete()  # only ours: the nodes' own lines vary
    start = datetime(2026, 11, 23, 14, 5, 6, 789000, tzinfo=timezone.utc)
    LogRecord.objects.bulk_create([
        LogRecord(robot=robot_row, logger=logger, level=level, message=message, stamp=start + timedelta(seconds=i))
        for i, (logger, level, message) in enumerate(LINES)
    ])
    with logged_in_page(browser, site, accept_downloads=True) as page:
        yield page


def shown(page: Page) -> list[str]:
    return page.locator(".log-line:visible .msg").all_inner_texts()


def query(page: Page) -> dict:
    """The page's address as the page itself has it (Playwright learns of replaceState late)."""
    return {k: v[0] for k, v in parse_qs(urlparse(page.evaluate("location.href")).query).items()}


def test_filters_count_what_is_shown_and_live_in_the_address(page, site):
    page.goto(f"{site}logs/robot/{ROBOT}/?level=WARN&node=lidar")
    status = page.locator('[data-log="status"]')
    # Others' live lines may arrive (the robot's nodes log); ours are the 3 lidar WARN lines.
    expect(page.locator(".log-line:visible", has_text="scan late")).to_have_count(3, timeout=WAIT_MS)
    assert shown(page) == ["scan late by 40 ms"] * 3
    total = page.locator(".log-line").count()
    expect(status).to_contain_text(f"3 of {total} lines shown")
    first_time = page.locator(".log-line:visible .t").first.inner_text()
    assert first_time == "2026-11-23 14:05:07.789 UTC"

    page.get_by_label("Nodes", exact=True).fill("")
    page.get_by_label("Hide nodes").fill("camera")
    page.get_by_label("Not").fill("goal")
    assert query(page) == {"level": "WARN", "xnode": "camera", "not": "goal"}
    assert shown(page) == ["scan late by 40 ms"] * 3
    # The address is the filter: a reload shows the same lines.
    page.reload()
    expect(page.get_by_label("Hide nodes")).to_have_value("camera")
    expect(page.locator(".log-line:visible", has_text="scan late")).to_have_count(3, timeout=WAIT_MS)
    assert "frame late" not in shown(page) and "no path to goal" not in shown(page)
    download = page.locator('[data-log="download"]').get_attribute("href")
    assert parse_qs(urlparse(download).query) == {"level": ["WARN"], "xnode": ["camera"], "not": ["goal"]}
    assert page.console_errors == []


def test_regular_expressions_are_applied_in_the_page_and_a_bad_one_is_named(page, site):
    page.goto(f"{site}logs/robot/{ROBOT}/")
    expect(page.locator(".log-line", has_text="scan ok")).to_have_count(3, timeout=WAIT_MS)
    page.get_by_label("Regular expressions").check()
    page.get_by_label("Text", exact=True).fill(r"^(scan|frame) late\b")
    page.get_by_label("Nodes", exact=True).fill("^(lidar|camera)_driver$")
    assert sorted(set(shown(page))) == ["frame late", "scan late by 40 ms"]
    assert query(page)["re"] == "1"
    error = page.locator('[data-log="error"]')
    expect(error).to_be_hidden()

    page.get_by_label("Not").fill("late(")
    expect(error).to_be_visible()
    expect(error).to_contain_text(re.compile(r"Not: not a valid regular expression \(.+\); it is ignored"))
    assert sorted(set(shown(page))) == ["frame late", "scan late by 40 ms"]  # the others still apply
    page.get_by_label("Not").fill("a" * 201)  # the field holds 200; typed in by script it is cut too
    assert len(page.get_by_label("Not").input_value()) == 200
    page.get_by_label("Not").fill("frame")
    expect(error).to_be_hidden()
    assert set(shown(page)) == {"scan late by 40 ms"}

    with page.expect_download() as done:
        page.locator('[data-log="download"]').click()
    text = open(done.value.path(), encoding="utf-8").read().splitlines()
    assert text[0].startswith(f"# /rosout of {ROBOT} (all nodes)")
    assert text[1].startswith("# filters: ") and text[1].endswith("as regular expressions, applied in the browser")
    assert text[2:] == [f"2026-11-23 14:05:{7 + 5 * i:02d}.789 UTC [WARN] [lidar_driver] scan late by 40 ms"
                        for i in range(3)]
    assert page.console_errors == []
