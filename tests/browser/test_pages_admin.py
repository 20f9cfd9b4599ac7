"""The admin in a real browser: a robot's nodes keep their ROS names and link to their
dashboard pages; no page (the admin's included) asks for an icon that is not there."""
from __future__ import annotations

import pytest
from playwright.sync_api import Page, expect

from lifecycle_site.fleet.models import ManagedNode, Robot
from tests.browser.conftest import ROBOT, submit_login
from tests.conftest import make_user

WAIT_MS = 20_000


@pytest.fixture
def admin_page(browser, site, robot):
    make_user("ada-admin", "admin")
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    page = context.new_page()
    page.missing = []
    page.on("response", lambda r: page.missing.append(r.url) if r.status == 404 else None)
    page.goto(site + "login/")
    submit_login(page, "ada-admin")
    expect(page.locator("h2", has_text=ROBOT)).to_be_visible(timeout=WAIT_MS)
    yield page
    context.close()


def test_a_robots_nodes_keep_their_names_and_link_to_their_pages(admin_page: Page, site):
    page = admin_page
    robot = Robot.objects.get(name=ROBOT)
    lidar = ManagedNode.objects.get(key=f"{ROBOT}.lidar_driver")
    page.goto(f"{site}admin/fleet/robot/{robot.pk}/change/")
    row = page.locator("tr.form-row", has=page.locator(f'input[name$="-id"][value="{lidar.pk}"]'))
    name = row.locator('input[name$="-name"]')
    expect(name).to_be_disabled()
    expect(name).to_have_value("/lidar_driver")
    row.get_by_role("link", name="node page").click()
    expect(page).to_have_url(f"{site}nodes/{ROBOT}.lidar_driver/")
    expect(page.locator("h1")).to_contain_text("lidar_driver")

    page.goto(f"{site}admin/fleet/managednode/{lidar.pk}/change/")
    expect(page.locator(".readonly", has_text="/lidar_driver").first).to_be_visible()
    page.get_by_role("link", name="View on site").click()
    expect(page).to_have_url(f"{site}nodes/{ROBOT}.lidar_driver/")


def test_no_page_asks_for_a_missing_icon(admin_page: Page, site):
    page = admin_page
    robot = Robot.objects.get(name=ROBOT)
    for path in ("", f"nodes/{ROBOT}.lidar_driver/", f"logs/robot/{ROBOT}/", "audit/", "tokens/", "admin/",
                 "admin/fleet/robot/", f"admin/fleet/robot/{robot.pk}/change/", "admin/api/apitoken/add/",
                 "api/v1/robots", "healthz", "no-such-page/"):
        page.goto(site + path)
        page.wait_for_load_state("load")
        page.wait_for_timeout(300)  # the icon is asked for after the load
    assert [url for url in page.missing if "favicon" in url] == []
    icons = page.evaluate("fetch(document.querySelector('link[rel=icon]')?.href || '/static/img/favicon.svg')"
                          ".then(r => r.status)")
    assert icons == 200
    # Where a document names no icon, browsers ask for /favicon.ico: it is the same icon.
    answer = page.goto(site + "favicon.ico")
    assert answer.status == 200 and answer.headers["content-type"].startswith("image/svg+xml")
