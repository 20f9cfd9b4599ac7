"""Keyboard and touch (issue 26, item 11): after a transition started from the keyboard on the
node page, the keyboard is still in its buttons (it went to the top of the page); every control
a finger uses is at least 44 px high on a phone; the node page's shutdown is red and kept apart
from the button before it, at both sizes."""
from __future__ import annotations

import pytest
from playwright.sync_api import Page, expect

from lifecycle_site.fleet.models import ManagedNode
from tests.browser.conftest import ARTIFACTS, COUNT_LIVE, ROBOT, logged_in_page, wait_live
from tests.integration.conftest import transition, wait_node

WAIT_MS = 30_000
PHONE = {"width": 390, "height": 844}
DESKTOP = {"width": 1440, "height": 900}
DANGER = "rgb(166, 27, 11)"  # --danger in site.css
MIN_GAP_PX = 16
# Visible controls shorter than 44 px: buttons, fields, the Logs and Timeline links, the links in a
# table's cards (an alert's node, logs and timeline) and the top navigation.
TOO_SMALL = """() => Array.from(document.querySelectorAll(
    'main button, main .button, main select, main input:not([type=hidden]):not([type=checkbox]), '
    + 'main .logs-link, main table.cards td a, header.top nav a, header.top nav button'))
  .filter((el) => el.getClientRects().length && getComputedStyle(el).visibility !== 'hidden')
  .map((el) => [(el.textContent.trim() || el.name || el.tagName).slice(0, 30),
                Math.round(el.getBoundingClientRect().height)])
  .filter(([, h]) => h < 44)"""




def live_node_page(page: Page, url: str) -> None:
    """The node page, once its socket's snapshot has redrawn the state panel (and its buttons)."""
    page.context.add_init_script(COUNT_LIVE)
    page.goto(url)
    wait_live(page, WAIT_MS)


def focused(page: Page) -> dict:
    return page.evaluate("""() => { const el = document.activeElement;
      return {tag: el.tagName, text: el.textContent.trim().slice(0, 40),
              inTransitions: !!el.closest('#node-state .transitions')}; }""")


def test_after_a_keyboard_transition_on_the_node_page_the_keyboard_stays_in_its_buttons(browser, site, robot, operator):
    key = f"{ROBOT}.camera_driver"
    assert ManagedNode.objects.get(key=key).state_label == "unconfigured"
    with logged_in_page(browser, site, viewport=DESKTOP) as page:
        live_node_page(page, f"{site}nodes/{key}/")
        configure = page.locator("#node-state").get_by_role("button", name="configure")
        configure.focus()
        page.keyboard.press("Enter")
        expect(page.locator("#transition-result")).to_contain_text("configure succeeded", timeout=WAIT_MS)
        expect(page.locator("#node-state .badge.big")).to_have_text("inactive")
        page.wait_for_timeout(500)  # live updates of the same change may still come
        assert focused(page)["inTransitions"], focused(page)
        # The next step from there, on the keyboard alone: activate.
        for _ in range(4):
            if focused(page)["text"] == "activate":
                break
            page.keyboard.press("Tab")
        page.keyboard.press("Enter")
        expect(page.locator("#node-state .badge.big")).to_have_text("active", timeout=WAIT_MS)
        page.wait_for_timeout(500)
        assert focused(page)["inTransitions"], focused(page)


@pytest.mark.parametrize("size", [DESKTOP, PHONE], ids=["desktop", "phone"])
def test_the_node_pages_shutdown_is_red_and_apart(browser, site, robot, operator, api, size):
    key = f"{ROBOT}.lidar_driver"
    for step in ("configure", "activate"):  # active: deactivate and shutdown side by side
        if ManagedNode.objects.get(key=key).state_label != "active":
            transition(api, key, step)
    wait_node(api, key, state="active")
    with logged_in_page(browser, site, viewport=size) as page:
        live_node_page(page, f"{site}nodes/{key}/")
        group = page.locator("#node-state .transitions")
        deactivate = group.get_by_role("button", name="deactivate")
        shutdown = group.get_by_role("button", name="shutdown")
        expect(shutdown).to_have_css("background-color", DANGER, timeout=WAIT_MS)
        left, right = deactivate.bounding_box(), shutdown.bounding_box()
        gap = right["x"] - (left["x"] + left["width"])
        assert gap >= MIN_GAP_PX or right["y"] >= left["y"] + left["height"], f"shutdown {gap:.0f} px from deactivate"
        page.screenshot(path=ARTIFACTS / f"node-shutdown-apart-{size['width']}.png")


PAGES = ["", "nodes/{robot}.flaky_node/", "alerts/", "audit/", "logs/node/{robot}.flaky_node/"]


@pytest.mark.parametrize("path", PAGES)
def test_touch_targets_are_at_least_44_px_on_a_phone(browser, site, robot, operator, path):
    with logged_in_page(browser, site, viewport=PHONE, device_scale_factor=1, is_mobile=True, has_touch=True) as page:
        page.goto(site + path.format(robot=ROBOT))
        page.wait_for_load_state("networkidle")
        if "nodes/" in path:
            expect(page.locator("#parameters")).to_be_visible(timeout=WAIT_MS)
        assert page.evaluate(TOO_SMALL) == []
        name = path.split("/")[0] or "fleet"
        page.screenshot(path=ARTIFACTS / f"phone-touch-{name}.png", full_page=True)
