"""The node page on a phone (390 x 844): parameters as cards that fit the screen, a select for
parameters with a fixed list of values, and a state graph whose labels stay readable."""
from __future__ import annotations

import re
from concurrent.futures import ThreadPoolExecutor

import pytest
from playwright.sync_api import Page, expect

from lifecycle_site.audit.models import ParameterRecord
from tests import stack
from tests.browser.conftest import ARTIFACTS, ROBOT, logged_in_page, submit_login

WAIT_MS = 30_000
PHONE = {"width": 390, "height": 844}


@pytest.fixture
def phone(browser, site, robot, operator):
    with logged_in_page(browser, site, viewport=PHONE, device_scale_factor=1, is_mobile=True,
                        has_touch=True) as page:
        yield page


def overflow(page: Page, selector: str) -> list[str]:
    """Elements matching ``selector`` that reach past the right edge of the screen."""
    return page.evaluate(
        """(selector) => Array.from(document.querySelectorAll(selector))
             .filter((el) => el.getClientRects().length && el.getBoundingClientRect().right > window.innerWidth + 0.5)
             .map((el) => (el.id || el.name || el.tagName) + ' ' + Math.round(el.getBoundingClientRect().right))""",
        selector,
    )


def test_parameters_are_cards_that_fit_a_phone_with_selects_for_fixed_lists(phone, site):
    page = phone
    page.goto(f"{site}nodes/{ROBOT}.flaky_node/")
    mode = page.locator('select[name="value:failure_mode"]')
    expect(mode).to_be_visible(timeout=WAIT_MS)
    # The list comes from the descriptor's additional_constraints ("one of: none, fail_configure, ...").
    assert mode.locator("option").all_inner_texts() == [
        "none", "fail_configure", "raise_activate", "error_in_error", "crash", "slow_configure", "hang"]
    expect(mode).to_have_value("fail_configure")
    # A bool parameter is a true/false select, not a checkbox one cannot tell is a field.
    sim_time = page.locator('select[name="value:use_sim_time"]')
    assert sim_time.locator("option").all_inner_texts() == ["true", "false"]
    expect(sim_time).to_have_value("false")
    # Ranges go onto the number field.
    seconds = page.locator('input[name="value:slow_seconds"]')
    assert (seconds.get_attribute("min"), seconds.get_attribute("max")) == ("0.0", "120.0")

    assert page.evaluate("document.documentElement.scrollWidth") <= PHONE["width"]
    assert overflow(page, "#parameters tr, #parameters input, #parameters select, #parameters button") == []
    page.screenshot(path=ARTIFACTS / "phone-parameters.png", full_page=True)

    mode.select_option("none")
    page.get_by_role("button", name="Save changes").click()
    expect(page.locator("#parameters")).to_contain_text("All changes accepted", timeout=WAIT_MS)
    expect(page.locator("#param-value-failure_mode")).to_have_text("none")
    record = ParameterRecord.objects.filter(node__key=f"{ROBOT}.flaky_node", name="failure_mode").first()
    assert (record.old_value, record.new_value) == ("fail_configure", "none")
    assert ParameterRecord.objects.filter(node__key=f"{ROBOT}.flaky_node", name="use_sim_time").count() == 0
    assert page.console_errors == []


def test_state_graph_labels_are_at_least_10_px_on_a_phone(phone, site):
    page = phone
    page.goto(f"{site}nodes/{ROBOT}.lidar_driver/")
    page.locator("details#node-machine > summary").click()  # folded away on a phone
    graph = page.locator("figure.graph svg:visible")
    expect(graph).to_have_count(1, timeout=WAIT_MS)
    sizes = page.evaluate(
        """() => {
             const svg = Array.from(document.querySelectorAll('figure.graph svg'))
               .find((s) => s.getClientRects().length);
             const scale = svg.getBoundingClientRect().width / svg.viewBox.baseVal.width;
             return Array.from(svg.querySelectorAll('text')).map((t) =>
               [t.textContent.trim(), parseFloat(getComputedStyle(t).fontSize) * scale]);
           }"""
    )
    assert len(sizes) == 17  # 10 states and 7 labelled transitions
    small = [(text, round(px, 1)) for text, px in sizes if px < 10]
    assert small == []
    assert page.evaluate("document.documentElement.scrollWidth") <= PHONE["width"]
    page.screenshot(path=ARTIFACTS / "phone-graph.png", full_page=True)  # the panel is redrawn live


def test_the_audit_page_shows_new_records_without_a_reload(browser, site, robot, operator, api):
    from tests.integration.conftest import transition

    context = browser.new_context(viewport={"width": 1280, "height": 900})
    page = context.new_page()
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.goto(site + "login/")
    submit_login(page, "bruno-operator")
    from lifecycle_site.fleet.models import ManagedNode

    # A state this module's gateway found that no record explains (the robot's processes and the
    # gateway are new with each module) becomes a record of its own within seconds: let it come first.
    stack.wait_for(lambda: ManagedNode.objects.get(key=f"{ROBOT}.camera_driver").unexplained_since is None, 20,
                   "the audit chain settled")
    with page.expect_websocket(lambda ws: "/ws/audit/" in ws.url):
        page.goto(f"{site}audit/?robot={ROBOT}&node=camera_driver")
    # What earlier modules recorded is on the page already: one more is expected.
    counted = re.match(r"\d+", page.locator("#audit-count").inner_text())
    shown = int(counted.group()) if counted else 0
    page.evaluate("window.__sameDocument = true")
    # Earlier modules may have left the node in any primary state: one step that is valid from it.
    state = ManagedNode.objects.get(key=f"{ROBOT}.camera_driver").state_label
    label, goal = {"unconfigured": ("configure", "inactive"), "inactive": ("cleanup", "unconfigured"),
                   "active": ("deactivate", "inactive")}[state]
    response = transition(api, f"{ROBOT}.camera_driver", label)
    assert response.status_code == 200, response.content
    count = f"{shown + 1} record" + ("s" if shown else "")
    expect(page.locator("#audit-count")).to_contain_text(count, timeout=WAIT_MS)
    row = page.locator("#audit-rows tr").first
    expect(row).to_contain_text(label)
    expect(row).to_contain_text("succeeded")
    expect(row).to_contain_text(f"{state} → {goal}")
    assert page.evaluate("window.__sameDocument") is True
    assert errors == []
    context.close()


def test_the_audit_pages_parameter_mode_shows_a_change_as_it_is_stored(browser, site, robot, operator, api):
    """Pushed, not found by the socket's 3 s read: the row is there well inside that period."""
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    page = context.new_page()
    page.goto(site + "login/")
    submit_login(page, "bruno-operator")
    with page.expect_websocket(lambda ws: "/ws/audit/" in ws.url):
        page.goto(f"{site}audit/?kind=parameters&robot={ROBOT}&node=camera_driver")
    page.wait_for_timeout(500)  # the socket's first read is done
    fps = 5.0 + ParameterRecord.objects.filter(name="fps").count() % 20  # a value it has not now
    # From another thread, as a request of the server is (this one runs Playwright's event loop).
    with ThreadPoolExecutor(1) as pool:
        changed = pool.submit(api.patch, f"/api/v1/nodes/{ROBOT}.camera_driver/parameters", {"fps": fps},
                              content_type="application/json").result()
    assert changed.status_code == 200, changed.content
    row = page.locator("#audit-rows tr").first
    expect(row).to_contain_text("fps", timeout=1_500)
    expect(row).to_contain_text(str(fps))
    context.close()
