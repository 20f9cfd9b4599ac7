"""Editing a parameter and running a bring-up from the pages, in a real browser."""
from __future__ import annotations

import re

from playwright.sync_api import expect

from lifecycle_site.audit.models import ParameterRecord
from tests.browser.conftest import ARTIFACTS, ROBOT, submit_login

WAIT_MS = 30_000


def test_edit_a_parameter_and_bring_up_the_robot(browser, site, robot, operator):
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.goto(site + "login/")
    submit_login(page, "bruno-operator")
    expect(page.locator("h2", has_text=ROBOT)).to_be_visible(timeout=WAIT_MS)

    # Parameters: the node's values with their constraints; a change is checked, sent and shown.
    page.goto(f"{site}nodes/{ROBOT}.lidar_driver/")
    field = page.get_by_label("scan_rate_hz", exact=True)
    expect(field).to_be_visible(timeout=WAIT_MS)
    expect(page.locator("#param-frame_id")).to_contain_text("read-only")
    field.fill("8")
    page.get_by_role("button", name="Save changes").click()
    expect(page.locator("#parameters")).to_contain_text("All changes accepted", timeout=WAIT_MS)
    expect(page.locator("#param-value-scan_rate_hz")).to_have_text("8.0")
    record = ParameterRecord.objects.filter(node__key=f"{ROBOT}.lidar_driver", name="scan_rate_hz").first()
    assert (record.new_value, record.source, record.requested_by_name) == (8.0, "dashboard", "bruno-operator")
    page.screenshot(path=ARTIFACTS / "node-parameters.png", full_page=True)

    # Bring up the whole robot, continuing past the node that fails, and watch it happen.
    with page.expect_websocket() as live:
        page.goto(site)
    # The live snapshot on connect redraws the robot sections (forms included): choose after it.
    live.value.wait_for_event("framereceived")
    section = page.locator(f"#robot-{ROBOT}")
    section.locator("select[name=policy]").select_option("continue")
    section.get_by_role("button", name="Bring up").click()
    run = section.locator(".run").first  # the newest: the page also lists recent runs
    expect(run).to_contain_text(re.compile("partial|partly"), timeout=WAIT_MS)
    expect(run).to_contain_text("/flaky_node")
    badge = page.locator("#node-" + f"{ROBOT}.camera_driver".replace(".", "__")).locator(".badge")
    expect(badge).to_have_text("active", timeout=WAIT_MS)
    page.screenshot(path=ARTIFACTS / "fleet-bringup.png", full_page=True)
    assert errors == []
    page.close()
