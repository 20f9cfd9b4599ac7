"""The operator's main path in German, in Chromium with a German browser: the login page, the
fleet page, a transition from a node's row, the node page, a robot-wide Shut down asked first
(and cancelled) in German, then the header's language choice back to English. ROS names (states,
transitions) stay as ROS writes them."""
from __future__ import annotations

import re

import pytest
from playwright.sync_api import expect

from lifecycle_site.audit.models import TransitionRecord
from tests import stack
from tests.browser.conftest import COUNT_LIVE, submit_login, wait_live, watched_page
from tests.conftest import make_user
from tests.integration.conftest import register, wait_node

WAIT_MS = 20_000
ROBOT = "de-agv"  # a robot of this module's own: its nodes start unconfigured
DOMAIN_OFFSET = 39  # also test_rosout_reader's (a unit test, later in the run; this one stops its nodes)


@pytest.fixture(scope="module")
def german_robot(gateway):
    from django.utils import timezone

    from lifecycle_site.fleet.models import Robot

    started = timezone.now()
    register(ROBOT, stack.domain(DOMAIN_OFFSET))
    process = stack.start_robot("de-nodes", stack.domain(DOMAIN_OFFSET), "lidar_driver,camera_driver")
    try:
        for node in ("lidar_driver", "camera_driver"):
            wait_node(None, f"{ROBOT}.{node}", alive=True, state="unconfigured", seen_since=started)
        yield ROBOT
    finally:
        process.stop()
        Robot.objects.filter(name=ROBOT).delete()


@pytest.fixture
def gerda(live_db):
    """An operator of this test's own: the language she chooses stays with her account."""
    user = make_user("gerda-operator", "operator")
    yield user
    user.delete()


def test_an_operators_day_in_german(browser, site, german_robot, gerda):
    key = f"{ROBOT}.lidar_driver"
    with watched_page(browser, page_errors=True, locale="de-DE") as page:  # Accept-Language: de-DE
        page.context.add_init_script(COUNT_LIVE)
        page.goto(site)
        expect(page.locator("html")).to_have_attribute("lang", "de")
        expect(page.get_by_role("heading", name="Anmelden")).to_be_visible()
        submit_login(page, "gerda-operator")
        expect(page.locator("h2", has_text=ROBOT)).to_be_visible(timeout=WAIT_MS)
        wait_live(page, WAIT_MS)
        expect(page.get_by_role("link", name="Flotte")).to_be_visible()
        expect(page.get_by_role("link", name="Änderungsprotokoll")).to_be_visible()

        # A transition from the fleet row: ROS's own words on the button and badge, ours in German.
        row = page.locator("#node-" + key.replace(".", "__"))
        expect(row.locator(".badge")).to_have_text("unconfigured", timeout=WAIT_MS)
        row.get_by_role("button", name=re.compile("^configure")).click()
        expect(row.locator(".badge")).to_have_text("inactive", timeout=WAIT_MS)
        expect(row.locator(".row-result")).to_contain_text("configure", timeout=WAIT_MS)
        assert TransitionRecord.objects.filter(requested_by=gerda).exists()
        assert TransitionRecord.objects.filter(node__key=key, source="dashboard", outcome="succeeded").exists()

        # A robot-wide Shut down is asked first, in German; cancelling sends nothing.
        section = page.locator(f"#robot-{ROBOT}")
        section.get_by_role("button", name="Herunterfahren").click()
        dialog = page.locator("dialog[open]")
        expect(dialog).to_contain_text(f"von {ROBOT} herunterfahren?")
        expect(dialog).to_contain_text("finalized")
        dialog.get_by_role("button", name="Abbrechen").click()
        expect(dialog).to_have_count(0)
        expect(row.locator(".badge")).to_have_text("inactive")

        # The node page: its headings and history in German.
        row.locator("a").first.click()
        expect(page.locator("h1")).to_contain_text("/lidar_driver")
        wait_live(page, WAIT_MS)
        expect(page.locator("main")).to_contain_text("Zustand")

        # The header's choice: English from now on, for this user.
        page.get_by_role("button", name="English").click()
        expect(page.locator("html")).to_have_attribute("lang", "en")
        expect(page.get_by_role("navigation", name="Main").get_by_role("link", name="Fleet")).to_be_visible()
        page.goto(site)
        expect(page.get_by_role("navigation", name="Main").get_by_role("link", name="Fleet")).to_be_visible()
        page.get_by_role("button", name="Deutsch").click()  # and back: the choice is kept with the user
        nav = page.get_by_role("navigation", name="Hauptnavigation")
        expect(nav.get_by_role("link", name="Flotte")).to_be_visible()
        assert not page.console_errors, page.console_errors
