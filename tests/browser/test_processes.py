"""A robot's processes page on the real stack: the gateway runs a launch profile (the demo robot's
nodes); the page, opened from the robot's header on the fleet page, shows it running with its
pid; Stop asks first (cancelled: nothing is sent; confirmed: it stops, on record), Start runs it
again under a new pid, and a crash and its respawn show without a reload."""
from __future__ import annotations

import os
import signal
import sys
from pathlib import Path

import pytest
from playwright.sync_api import Page, expect

from lifecycle_site.audit.models import ProcessRecord
from lifecycle_site.fleet.models import ProcessProfile, Robot
from tests import stack
from tests.browser.conftest import ARTIFACTS, COUNT_LIVE, PHONE, submit_login, wait_live, watched_page
from tests.integration.conftest import register

ROBOT = "br-proc"
PROCESS = "drivers"
# Every offset 0-35 is some test's; 35 is tests/integration/test_processes.py's, and no other browser
# module's (this module's robot is deleted at its end, before that one registers its own).
DOMAIN = 35
WAIT_MS = 30_000


def profile() -> ProcessProfile:
    return ProcessProfile.objects.get(robot__name=ROBOT, name=PROCESS)


def running_pid(other_than: int | None = None) -> int:
    """The pid the gateway reports once the process runs (a new one: ``other_than`` another)."""
    found = stack.wait_for(lambda: (p := profile()).status == "running" and p.pid not in (None, other_than) and p.pid,
                           30, "the process to run")
    return int(found)


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except (ProcessLookupError, FileNotFoundError):
        return False


def ours(pid: int) -> bool:
    """Still the demo robot this module had started (a pid may be reused once it is gone)."""
    try:
        return "ros_gateway.demo.robot" in Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
    except OSError:
        return False


def on_record() -> int:
    return ProcessRecord.objects.filter(robot_name=ROBOT).count()


@pytest.fixture(scope="module")
def supervised(gateway):
    """The robot and its launch profile, run by the gateway; the pids it has had (the test adds
    the later ones). At the end the profile goes, the gateway stops the process (or, should it
    not within the bound, the module kills what is left), and the robot is deleted."""
    robot = register(ROBOT, stack.domain(DOMAIN))
    pids: set[int] = set()
    try:
        ProcessProfile.objects.create(
            robot=robot, name=PROCESS, command=sys.executable, cwd=str(stack.ROOT), stop_grace_s=5.0,
            respawn_delay_s=0.5,
            args=["-m", "ros_gateway.demo.robot", "--domain", str(stack.domain(DOMAIN)), "--nodes", "lidar_driver"],
            env={"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"})
        Robot.objects.get(pk=robot.pk).save()  # (saving the robot publishes its gateway's config again)
        pids.add(running_pid())
        yield pids
    finally:
        pids.update(ProcessProfile.objects.filter(robot=robot).exclude(pid=None).values_list("pid", flat=True))
        ProcessProfile.objects.filter(robot=robot).delete()
        Robot.objects.get(pk=robot.pk).save()
        try:
            stack.wait_for(lambda: not any(alive(pid) for pid in pids), 30, "the gateway to stop the process")
        finally:
            for pid in pids:
                if alive(pid) and ours(pid):
                    os.killpg(pid, signal.SIGKILL)  # (its own process group: the supervisor starts it so)
            Robot.objects.filter(pk=robot.pk).delete()  # later modules see the fleet without it


@pytest.fixture
def page(browser, operator):
    with watched_page(browser, page_errors=True, viewport={"width": 1440, "height": 900}) as page:
        yield page


def errors_of(page: Page) -> list[str]:
    """The page's console errors, but for a poll abandoned for a button (hx-sync: htmx logs
    "htmx:sendAbort" when a button is pressed while a poll is under way)."""
    return [e for e in page.console_errors if "htmx:sendAbort" not in e]


def row_of(page: Page):
    return page.locator(f"tr.process-row[data-process='{PROCESS}']")


def button(row, action: str):
    """The row's button for ``action``, by its accessible name ("Stop drivers on br-proc")."""
    return row.get_by_role("button", name=f"{action} {PROCESS} on {ROBOT}", exact=True)


def test_stop_asks_first_and_start_runs_it_again(page: Page, site, supervised):
    pid = running_pid()
    page.context.add_init_script(COUNT_LIVE)
    page.goto(site)
    submit_login(page, "bruno-operator")
    wait_live(page, WAIT_MS)  # the fleet page, redrawn live
    head = page.locator(f"#robot-{ROBOT} .robot-head")
    head.screenshot(path=ARTIFACTS / "processes-fleet-link.png")
    head.get_by_role("link", name="Processes").click()
    expect(page.locator("h1")).to_contain_text(f"Processes of {ROBOT}", timeout=WAIT_MS)
    row = row_of(page)
    expect(row.locator(".proc-status")).to_have_text("running", timeout=WAIT_MS)
    expect(row.locator("td[data-label=PID]")).to_have_text(str(pid))
    expect(row.locator("th")).to_contain_text("ros_gateway.demo.robot --domain")
    expect(button(row, "Start")).to_have_count(0)
    expect(row.locator(".process-nodes")).to_have_text("nodes: /lidar_driver", timeout=WAIT_MS)  # attributed
    page.screenshot(path=ARTIFACTS / "processes-running.png", full_page=True)

    # Stop, cancelled: nothing is sent, nothing is on record.
    before = on_record()
    dialog = page.locator("dialog#confirm-dialog")
    button(row, "Stop").click()
    expect(dialog).to_be_visible()
    expect(dialog).to_contain_text(f"Stop {PROCESS} on {ROBOT}?")
    expect(dialog).to_contain_text("Its nodes stop with it: /lidar_driver.")
    expect(dialog).to_contain_text("stays stopped until someone starts it again")
    page.screenshot(path=ARTIFACTS / "processes-confirm-stop.png")
    dialog.get_by_role("button", name="Cancel", exact=True).click()
    expect(dialog).to_be_hidden()
    page.wait_for_timeout(1_500)  # a request sent would be on record by now
    assert on_record() == before
    assert (profile().status, profile().pid) == ("running", pid) and alive(pid)
    expect(row.locator(".proc-status")).to_have_text("running")

    # Stop, confirmed: the row says stopped, the answer and the records say who stopped it.
    button(row, "Stop").click()
    dialog.get_by_role("button", name="Stop", exact=True).click()
    expect(row.locator(".proc-status")).to_have_text("stopped", timeout=WAIT_MS)
    expect(page.locator("#process-result .result.ok")).to_contain_text("stopped", timeout=WAIT_MS)
    expect(row.locator("th")).to_be_focused()  # the keyboard is on the row (its Stop button is gone)
    stop = ProcessRecord.objects.filter(robot_name=ROBOT, action="stop", source="dashboard").latest("at")
    assert (stop.outcome, stop.requested_by_name, stop.old_pid) == ("succeeded", "bruno-operator", pid)
    first = page.locator("#process-records tr").first
    expect(first).to_contain_text("stop")
    expect(first).to_contain_text("bruno-operator")
    expect(row.locator("td[data-label=PID]")).to_have_text("—")
    assert not alive(pid)
    expect(button(row, "Stop")).to_have_count(0)

    # Start: running again, under a new pid.
    button(row, "Start").click()
    expect(row.locator(".proc-status")).to_have_text("running", timeout=WAIT_MS)
    started = running_pid(other_than=pid)
    supervised.add(started)
    expect(row.locator("td[data-label=PID]")).to_have_text(str(started))
    expect(page.locator("#process-result .result.ok")).to_contain_text(f"started as pid {started}")
    start = ProcessRecord.objects.filter(robot_name=ROBOT, action="start", source="dashboard").latest("at")
    assert (start.outcome, start.pid, start.requested_by_name) == ("succeeded", started, "bruno-operator")
    page.screenshot(path=ARTIFACTS / "processes-started.png", full_page=True)
    assert errors_of(page) == [], page.console_errors


def test_a_crash_and_its_respawn_show_without_a_reload(page: Page, site, supervised):
    pid = running_pid()
    page.goto(f"{site}robots/{ROBOT}/processes/")
    submit_login(page, "bruno-operator")
    row = row_of(page)
    expect(row.locator("td[data-label=PID]")).to_have_text(str(pid), timeout=WAIT_MS)
    page.evaluate("window.sameDocument = true")  # gone after a reload
    os.kill(pid, signal.SIGKILL)
    respawned = running_pid(other_than=pid)
    supervised.add(respawned)
    expect(row.locator("td[data-label=PID]")).to_have_text(str(respawned), timeout=WAIT_MS)
    expect(row.locator(".proc-status")).to_have_text("running")
    expect(row.locator("td[data-label='Last exit']")).to_contain_text("SIGKILL")
    records = page.locator("#process-records")
    expect(records).to_contain_text("respawned")
    expect(records).to_contain_text("supervisor (by itself)")
    assert page.evaluate("window.sameDocument") is True
    page.set_viewport_size(PHONE)  # one card per process and per record
    page.screenshot(path=ARTIFACTS / "processes-phone.png", full_page=True)
    assert errors_of(page) == [], page.console_errors
