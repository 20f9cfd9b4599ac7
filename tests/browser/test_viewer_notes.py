"""A viewer is told why there are no buttons (issue 26, item 10): where the fleet's group
operations and transitions would be, and where an alert's Acknowledge would be, as the node
page already does; an operator sees the buttons and no such note."""
from __future__ import annotations

import pytest
from playwright.sync_api import expect

from lifecycle_site.alerts.models import Alert, Rule
from lifecycle_site.fleet.models import Robot
from tests import stack
from tests.browser.conftest import ARTIFACTS, ROBOT, logged_in_page
from tests.conftest import make_user

WAIT_MS = 30_000
ROLE_NOTE = "needs the operator role"


@pytest.fixture(scope="module")
def viewer(live_db):
    return make_user("vera-viewer", "viewer")


@pytest.fixture(scope="module")
def firing(robot):
    """flaky_node stays unconfigured (fail_configure): this rule's alert fires and stays."""
    rule = Rule.objects.create(name="br-viewer-notes", kind=Rule.Kind.STATE, state="unconfigured",
                               robot=Robot.objects.get(name=ROBOT), node_pattern="/flaky_node")
    stack.wait_for(lambda: Alert.objects.filter(rule=rule, status="firing").first(), 20, "the alert to fire")
    yield Alert.objects.get(rule=rule)
    rule.delete()
    Alert.objects.filter(rule_name="br-viewer-notes").delete()


@pytest.mark.parametrize("size", [{"width": 1440, "height": 900}, {"width": 390, "height": 844}],
                         ids=["desktop", "phone"])
def test_a_viewer_is_told_why_there_are_no_buttons(browser, site, robot, viewer, firing, size):
    with logged_in_page(browser, site, "vera-viewer", viewport=size) as page:
        section = page.locator(f"#robot-{ROBOT}")
        expect(section.get_by_role("button", name="Bring up")).to_have_count(0)
        note = section.locator(".role-note")
        expect(note).to_contain_text(ROLE_NOTE, timeout=WAIT_MS)
        expect(note).to_contain_text("transitions")
        # Where the buttons would be: above the nodes' table, in the robot's own section.
        assert note.bounding_box()["y"] < section.locator("table.nodes").bounding_box()["y"]
        section.locator("h2").first.scroll_into_view_if_needed()  # (robots of earlier modules may come first)
        expect(note).to_be_in_viewport()
        page.screenshot(path=ARTIFACTS / f"viewer-fleet-{size['width']}.png", full_page=True)

        page.goto(site + "alerts/")
        row = page.locator(f"#alert-{firing.id}")
        expect(row.get_by_role("button", name="Acknowledge")).to_have_count(0)
        expect(row).to_contain_text(f"Acknowledging {ROLE_NOTE}")
        page.screenshot(path=ARTIFACTS / f"viewer-alerts-{size['width']}.png", full_page=True)


def test_an_operator_sees_the_buttons_and_no_note(browser, site, robot, operator, firing):
    with logged_in_page(browser, site) as page:
        expect(page.locator(f"#robot-{ROBOT}").get_by_role("button", name="Bring up")).to_be_visible()
        expect(page.locator(".role-note")).to_have_count(0)
        page.goto(site + "alerts/")
        row = page.locator(f"#alert-{firing.id}")
        expect(row.get_by_role("button", name="Acknowledge")).to_be_visible()
        expect(row).not_to_contain_text(ROLE_NOTE)
