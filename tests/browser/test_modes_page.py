"""A robot's Modes page with real nodes: Apply asks first (cancelled: nothing is sent), then runs the
mode as one run shown on the page; drift made behind its back appears without a reload; the page
fits a phone."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from django.utils import timezone
from playwright.sync_api import expect

from lifecycle_site.fleet.models import GroupRun, ManagedNode
from lifecycle_site.modes.models import CurrentMode, Mode
from tests import stack
from tests.browser.conftest import ARTIFACTS, PHONE, ROBOT, logged_in_page

WAIT_MS = 30_000
MODE = "br-inspection"
ROS_CALL = Path(__file__).resolve().parents[1] / "integration" / "ros_call.py"


@pytest.fixture
def mode(robot):
    found = Mode.objects.create(name=MODE, description="Lidar scanning fast, camera ready", nodes={
        "/lidar_driver": {"state": "active", "parameters": {"scan_rate_hz": 9.0}},
        "/camera_driver": {"state": "inactive"},
        "/flaky_node": {"state": None}})
    found.robots.add(ManagedNode.objects.get(key=f"{ROBOT}.lidar_driver").robot)
    yield found
    # Later modules find the robot as the fixture made it: no mode, no desired states.
    CurrentMode.objects.filter(robot__name=ROBOT).delete()
    found.delete()
    ManagedNode.objects.filter(robot__name=ROBOT).update(desired_state="")


def test_apply_asks_first_runs_the_mode_and_drift_shows_without_a_reload(browser, site, robot, operator, mode):
    with logged_in_page(browser, site) as page:
        page.goto(f"{site}robots/{ROBOT}/modes/")
        expect(page.locator("#modes-live")).to_contain_text("is in no mode yet")
        article = page.locator(f"#mode-{MODE}")
        expect(article).to_contain_text("scan_rate_hz=9.0")
        runs = GroupRun.objects.filter(robot__name=ROBOT, operation="mode")
        before = runs.count()

        article.get_by_role("button", name=f"Apply {MODE}").click()
        dialog = page.locator("dialog#confirm-dialog")
        expect(dialog).to_contain_text(f"Apply mode {MODE} to {ROBOT}?")
        dialog.get_by_role("button", name="Cancel").click()
        expect(dialog).to_be_hidden()
        page.wait_for_timeout(1_000)
        assert runs.count() == before  # cancelled: nothing sent

        article.get_by_role("button", name=f"Apply {MODE}").click()
        dialog.get_by_role("button", name=f"Apply {MODE}").click()
        expect(page.locator("#mode-result")).to_contain_text(f"Applying mode {MODE} to {ROBOT}", timeout=WAIT_MS)
        live = page.locator("#modes-live")
        expect(live).to_contain_text("Every node is as the mode says", timeout=WAIT_MS)
        expect(live.locator(".run")).to_contain_text("succeeded", timeout=WAIT_MS)
        expect(live.locator(".run")).to_contain_text("set parameters ✓")
        assert runs.count() == before + 1

        # Another tool (a process of the test's own, as `ros2 lifecycle set` is) deactivates the
        # lidar: the page shows the difference without a reload.
        done = subprocess.run([sys.executable, str(ROS_CALL), str(stack.domain(7)), "/lidar_driver", "4"],
                              capture_output=True, text=True, timeout=60, env=stack.environment())
        assert "success" in done.stdout, done.stdout + done.stderr
        row = live.locator("table.drift tr.drift-state")
        expect(row).to_contain_text("/lidar_driver", timeout=10_000)
        expect(row).to_contain_text("inactive")
        expect(live).to_contain_text("1 difference")
        assert page.console_errors == []

    with logged_in_page(browser, site, viewport=PHONE, device_scale_factor=1, is_mobile=True,
                        has_touch=True) as phone:
        phone.goto(f"{site}robots/{ROBOT}/modes/")
        expect(phone.locator("table.drift")).to_be_visible()
        assert phone.evaluate("document.documentElement.scrollWidth") <= PHONE["width"]
        phone.screenshot(path=ARTIFACTS / "phone-modes.png", full_page=True)


def test_the_node_page_sets_the_keep_policy_and_resumes_a_node_left_alone(browser, site, robot, operator):
    """The node page's "kept against other tools" select saves as it changes; a node its gateway
    left alone after a fight says so with the gateway's words and a button that resumes it."""
    key = f"{ROBOT}.camera_driver"
    try:
        with logged_in_page(browser, site) as page:
            page.goto(f"{site}nodes/{key}/")
            panel = page.locator("#desired-state")
            panel.locator('select[name="keep_desired"]').select_option("enforce")
            expect(panel).to_contain_text("Saved.", timeout=WAIT_MS)
            assert ManagedNode.objects.get(key=key).keep_desired == "enforce"
            # What the ingest stores when the gateway gives up (ros_gateway/desired_keeper.py).
            ManagedNode.objects.filter(key=key).update(
                enforcement_stopped=timezone.now(),
                enforcement_note="another manager keeps changing /camera_driver (moved away 4 times in 10 min)")
            page.reload()
            panel = page.locator("#desired-state")
            expect(panel).to_contain_text("another manager keeps changing /camera_driver")
            panel.get_by_role("button", name="Resume keeping it").click()
            expect(panel).to_contain_text("Saved.", timeout=WAIT_MS)
            expect(panel).not_to_contain_text("another manager keeps changing")
            node = ManagedNode.objects.get(key=key)
            assert node.enforcement_stopped is None and node.enforcement_resumed is not None
            assert page.console_errors == []
    finally:
        ManagedNode.objects.filter(key=key).update(keep_desired="", enforcement_stopped=None, enforcement_note="")
