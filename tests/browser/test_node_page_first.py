"""The node page leads with what matters (issue 26, item 4), in Chromium on the real stack: its
state, its last outcome and the node's own reason come first, then the actions; the state
machine drawing and the list of states are folded away on a phone (open on a desktop)."""
from __future__ import annotations

import re

from playwright.sync_api import Page, expect

from lifecycle_site.audit.models import TransitionRecord
from tests import stack
from tests.browser.conftest import ARTIFACTS, DESKTOP, PHONE, ROBOT, sized_page, wait_live
from tests.integration.conftest import transition, wait_node

WAIT_MS = 30_000
KEY = f"{ROBOT}.flaky_node"
REASON = re.compile("simulated hardware not found on /dev/ttyFLAKY")


def open_node(browser, site: str, viewport: dict) -> Page:
    page = sized_page(browser, site, viewport, f"nodes/{KEY}/")
    # Measured once the socket's snapshot has redrawn the state panel (a badge found before is gone after).
    wait_live(page, WAIT_MS)
    expect(page.locator("#node-state .badge.big")).to_have_text("unconfigured", timeout=WAIT_MS)
    return page


def top(page: Page, locator) -> float:
    box = locator.bounding_box()
    assert box is not None, locator
    return box["y"]


def failed_configure(api) -> TransitionRecord:
    wait_node(None, KEY, alive=True, state="unconfigured")
    before = TransitionRecord.objects.filter(node__key=KEY).count()
    transition(api, KEY, "configure")  # failure_mode=fail_configure: it stays unconfigured, with its reason
    return stack.wait_for(lambda: TransitionRecord.objects.filter(node__key=KEY).count() > before
                          and TransitionRecord.objects.filter(node__key=KEY).first(), 15, "the failed configure")


def test_state_last_outcome_and_reason_come_before_the_actions_and_the_drawing(browser, site, robot, operator, api):
    record = failed_configure(api)
    assert record.outcome == "failed", record.outcome
    for viewport, name in ((PHONE, "phone"), (DESKTOP, "desktop")):
        page = open_node(browser, site, viewport)
        reason = page.locator("main").get_by_text(REASON).first
        expect(reason).to_be_visible()
        expect(reason).to_be_in_viewport()  # on the first screen, without scrolling
        last = page.locator("#node-last")
        expect(last).to_contain_text("configure failed")
        expect(last).to_contain_text("fail_configure")  # the node's own words, not only "failed"
        badge, button = page.locator("#node-state .badge.big"), page.get_by_role("button", name="configure", exact=True)
        assert top(page, badge) < top(page, reason) < top(page, button), name
        machine = page.locator("details#node-machine")
        graph = page.locator("figure.graph")
        if viewport is PHONE:
            expect(button).to_be_in_viewport()
            expect(machine).not_to_have_attribute("open", "")  # folded away
            expect(graph).to_be_hidden()
            page.screenshot(path=ARTIFACTS / "node-first-phone.png", full_page=False)
            machine.locator("summary").click()  # a tap opens it
            expect(graph).to_be_visible()
            assert page.evaluate("document.documentElement.scrollWidth") <= PHONE["width"]
        else:
            expect(machine).to_have_attribute("open", "")
            expect(graph).to_be_visible()
            assert top(page, button) < top(page, graph)
            page.screenshot(path=ARTIFACTS / "node-first-desktop.png", full_page=True)
        assert page.console_errors == [], page.console_errors
        page.context.close()


def test_the_last_outcome_follows_live_and_a_push_keeps_the_drawing_as_the_user_left_it(browser, site, robot,
                                                                                       operator, api):
    page = open_node(browser, site, PHONE)
    machine = page.locator("details#node-machine")
    machine.locator("summary").click()
    expect(machine).to_have_attribute("open", "")
    answer = api.patch(f"/api/v1/nodes/{KEY}/parameters", {"failure_mode": "none"}, content_type="application/json")
    assert answer.status_code == 200, answer.content
    try:
        assert transition(api, KEY, "configure").status_code == 200
        expect(page.locator("#node-state .badge.big")).to_have_text("inactive", timeout=WAIT_MS)
        expect(page.locator("#node-last")).to_contain_text("configure succeeded", timeout=WAIT_MS)
        expect(page.locator("#node-last")).not_to_contain_text("fail_configure")
        expect(machine).to_have_attribute("open", "")  # the live update did not fold it again
        expect(page.locator("#node-machine ul.states li.current")).to_contain_text("inactive")
        assert page.console_errors == [], page.console_errors
    finally:
        transition(api, KEY, "cleanup")
        api.patch(f"/api/v1/nodes/{KEY}/parameters", {"failure_mode": "fail_configure"},
                  content_type="application/json")
        page.context.close()
