"""Dangerous actions ask first, in a dialog of the page's own (issue 26, item 1): the robot-wide
Reset and Shut down, the per-node shutdown on a fleet row and on the node page. Each is clicked
and cancelled (with the button, with Esc: nothing is sent, nothing is on record) and confirmed
(it runs), with a mouse, the keyboard and a finger; the dialog names the robot and how many nodes."""
from __future__ import annotations

import re

import pytest
from playwright.sync_api import Page, expect

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import GroupRun, ManagedNode
from tests import stack
from tests.browser.conftest import ARTIFACTS, COUNT_LIVE, ROBOT, live_page, logged_in_page

WAIT_MS = 30_000
PHONE = {"width": 390, "height": 844}
NODES = ("lidar_driver", "camera_driver", "flaky_node")  # the lifecycle nodes of the robot fixture


def dom(key: str) -> str:
    return "#node-" + key.replace(".", "__")


def on_record() -> tuple[int, int]:
    """What was sent to the robot, by the audit log and the run list: unchanged if nothing was
    sent (a change the site only observed, say one an earlier module made, does not count)."""
    sent = TransitionRecord.objects.filter(robot_name=ROBOT).exclude(outcome=TransitionRecord.Outcome.OBSERVED)
    return (sent.count(),
            GroupRun.objects.filter(robot__name=ROBOT).count())


def states() -> dict[str, str]:
    return dict(ManagedNode.objects.filter(robot__name=ROBOT, name__in=[f"/{n}" for n in NODES])
                .values_list("name", "state_label"))


def live_fleet(page: Page, site: str) -> None:
    live_page(page, site)


def nothing_sent(page: Page, before: tuple[int, int], shown: dict[str, str]) -> None:
    page.wait_for_timeout(1_500)  # a request sent would be on record by now
    assert on_record() == before
    assert states() == shown


def recorded(key: str, label: str) -> None:
    """The confirmed transition is on record, once (the ingest stores it a moment later)."""
    ours = TransitionRecord.objects.filter(node__key=key, transition_label=label, requested_by_name="bruno-operator")
    stack.wait_for(lambda: ours.exists(), 10, f"{label} of {key} on record")
    assert ours.count() == 1


def height(locator) -> float:
    return locator.evaluate("el => el.getBoundingClientRect().height")


@pytest.fixture
def desktop(browser, site, robot, operator):
    with logged_in_page(browser, site, viewport={"width": 1440, "height": 900}) as page:
        page.context.add_init_script(COUNT_LIVE)
        yield page


@pytest.fixture
def phone(browser, site, robot, operator):
    with logged_in_page(browser, site, viewport=PHONE, device_scale_factor=1, is_mobile=True, has_touch=True) as page:
        page.context.add_init_script(COUNT_LIVE)
        yield page


def test_a_row_shutdown_on_a_phone_asks_with_buttons_a_finger_can_hit(phone: Page, site):
    page = phone
    live_fleet(page, site)
    section = page.locator(f"#robot-{ROBOT}")
    for name in ("Bring up", "Pause", "Resume", "Reset", "Shut down"):
        assert height(section.get_by_role("button", name=name, exact=True)) >= 44, name
    row = page.locator(dom(f"{ROBOT}.flaky_node"))
    shutdown = row.get_by_role("button", name=re.compile("^shutdown"))
    assert height(shutdown) >= 44
    before, shown = on_record(), states()

    shutdown.tap()
    dialog = page.locator("dialog#confirm-dialog")
    expect(dialog).to_be_visible()
    expect(dialog).to_contain_text(f"Shut down /flaky_node on {ROBOT}?")
    expect(dialog).to_contain_text("finalized")
    cancel, confirm = dialog.get_by_role("button", name="Cancel"), dialog.get_by_role("button", name="Shut down")
    assert height(cancel) >= 44 and height(confirm) >= 44
    assert dialog.evaluate("el => el.getBoundingClientRect().right") <= PHONE["width"]
    page.screenshot(path=ARTIFACTS / "phone-confirm-row-shutdown.png")
    cancel.tap()
    expect(dialog).to_be_hidden()
    nothing_sent(page, before, shown)

    shutdown.tap()
    expect(dialog).to_be_visible()
    dialog.get_by_role("button", name="Shut down").tap()
    expect(row.locator(".badge")).to_have_text("finalized", timeout=WAIT_MS)
    recorded(f"{ROBOT}.flaky_node", "shutdown")


def test_node_page_shutdown_asks_naming_node_and_robot(desktop: Page, site):
    page = desktop
    key = f"{ROBOT}.lidar_driver"
    live_page(page, f"{site}nodes/{key}/")
    button = page.locator("#node-state").get_by_role("button", name="shutdown")
    before, shown = on_record(), states()
    button.click()
    dialog = page.locator("dialog#confirm-dialog")
    expect(dialog).to_be_visible()
    expect(dialog).to_contain_text(f"Shut down /lidar_driver on {ROBOT}?")
    page.screenshot(path=ARTIFACTS / "desktop-confirm-node-shutdown.png")
    dialog.get_by_role("button", name="Cancel").click()
    expect(dialog).to_be_hidden()
    nothing_sent(page, before, shown)

    button.click()
    dialog.get_by_role("button", name="Shut down").click()
    expect(page.locator("#node-state .badge.big")).to_have_text("finalized", timeout=WAIT_MS)
    recorded(key, "shutdown")


def test_robot_wide_reset_and_shutdown_ask_with_the_robot_and_its_node_count(desktop: Page, site):
    page = desktop
    live_fleet(page, site)
    section = page.locator(f"#robot-{ROBOT}")
    dialog = page.locator("dialog#confirm-dialog")
    # No bring-up order (an earlier module may have set one): the runs take every node side by
    # side, so that a node finalized above fails alone and the others are still driven.
    ManagedNode.objects.filter(robot__name=ROBOT).update(order=None)
    before, shown = on_record(), states()
    # Its nodes as its rows show them (earlier modules may have left one of their own behind).
    count = ManagedNode.objects.filter(robot__name=ROBOT).exclude(first_seen__isnull=True).count()
    assert count >= len(NODES)

    # Reset with the mouse, cancelled with the dialog's button.
    section.get_by_role("button", name="Reset", exact=True).click()
    expect(dialog).to_be_visible(timeout=5_000)
    expect(dialog).to_contain_text(f"Reset all {count} nodes of {ROBOT} to unconfigured?")
    page.screenshot(path=ARTIFACTS / "desktop-confirm-robot-reset.png")
    dialog.get_by_role("button", name="Cancel").click()
    expect(dialog).to_be_hidden()
    nothing_sent(page, before, shown)

    # Shut down from the keyboard: the dialog opens on Cancel (Enter there is safe), Esc closes
    # it, and the keyboard is back on the button it came from.
    shutdown = section.get_by_role("button", name="Shut down", exact=True)
    shutdown.focus()
    page.keyboard.press("Enter")
    expect(dialog).to_be_visible()
    expect(dialog).to_contain_text(f"Shut down all {count} nodes of {ROBOT}?")
    expect(dialog).to_contain_text("only a restart of their processes brings them back")
    expect(dialog.get_by_role("button", name="Cancel")).to_be_focused()
    page.screenshot(path=ARTIFACTS / "desktop-confirm-robot-shutdown.png")
    page.keyboard.press("Escape")
    expect(dialog).to_be_hidden()
    expect(shutdown).to_be_focused()
    page.keyboard.press("Enter")
    expect(dialog).to_be_visible()
    page.keyboard.press("Enter")  # on Cancel
    expect(dialog).to_be_hidden()
    nothing_sent(page, before, shown)

    # Confirmed: Reset runs (mouse), then Shut down (Tab to the dialog's Shut down, Enter).
    section.get_by_role("button", name="Reset", exact=True).click()
    dialog.get_by_role("button", name="Reset").click()
    # It ran (its nodes finalized by the tests above fail it: that is the point of asking).
    expect(section.locator(".run").first).to_contain_text(f"Reset of {ROBOT}", timeout=WAIT_MS)
    assert GroupRun.objects.filter(robot__name=ROBOT).first().operation == "reset"

    # Restart all, the operation added by an entry of the shared table alone, asks as well.
    before = on_record()
    section.get_by_role("button", name="Restart all", exact=True).click()
    expect(dialog).to_contain_text(f"Restart all {count} nodes of {ROBOT}?")
    expect(dialog).to_contain_text("then configured and activated again in order")
    dialog.get_by_role("button", name="Cancel").click()
    assert on_record() == before
    section.get_by_role("button", name="Restart all", exact=True).click()
    dialog.get_by_role("button", name="Restart all").click()
    expect(section.locator(".run").first).to_contain_text(f"Full restart of {ROBOT}", timeout=WAIT_MS)
    expect(section.locator(".run").first).to_have_attribute("data-done", "true", timeout=WAIT_MS)
    assert GroupRun.objects.filter(robot__name=ROBOT).first().operation == "restart_all"

    shutdown.focus()
    page.keyboard.press("Enter")
    expect(dialog).to_be_visible()
    page.keyboard.press("Tab")
    expect(dialog.get_by_role("button", name="Shut down")).to_be_focused()
    page.keyboard.press("Enter")
    expect(dialog).to_be_hidden()
    for node in NODES:
        expect(page.locator(dom(f"{ROBOT}.{node}")).locator(".badge")).to_have_text("finalized", timeout=WAIT_MS)
    run = GroupRun.objects.filter(robot__name=ROBOT).first()
    assert (run.operation, run.requested_by.username) == ("shutdown", "bruno-operator")
