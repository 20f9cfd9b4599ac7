"""What an operator does all day, in a real browser, directly and behind the sub-path proxy."""
from __future__ import annotations

import re

import pytest
from playwright.sync_api import Page, expect

from lifecycle_site.audit.models import TransitionRecord
from tests.browser.conftest import ARTIFACTS, COUNT_LIVE, ROBOT, submit_login, wait_live, watched_page

WAIT_MS = 20_000


def dom_id(key: str) -> str:
    return "#node-" + key.replace(".", "__")


@pytest.fixture(params=["direct", "proxied"])
def base_url(request, site, proxied_site, robot, operator):
    return (site if request.param == "direct" else proxied_site), request.param


@pytest.fixture
def page(browser):
    with watched_page(browser, page_errors=True) as page:
        page.context.add_init_script(COUNT_LIVE)
        yield page


def log_in(page: Page, base: str) -> None:
    page.goto(base)
    expect(page).to_have_url(re.compile(r"/login/"))
    submit_login(page, "bruno-operator")
    expect(page.locator("h2", has_text=ROBOT)).to_be_visible(timeout=WAIT_MS)
    wait_live(page, WAIT_MS)


def test_operator_flow(page: Page, base_url):
    base, mode = base_url
    # Each pass drives a node of its own, so both start from unconfigured.
    node = "lidar_driver" if mode == "direct" else "camera_driver"
    key = f"{ROBOT}.{node}"
    ours = TransitionRecord.objects.filter(node__key=key, source="dashboard", outcome="succeeded")
    before = ours.count()
    log_in(page, base)
    row = page.locator(dom_id(key))
    expect(row.locator(".badge")).to_have_text("unconfigured", timeout=WAIT_MS)
    expect(page.locator("#gateway-banner")).to_be_hidden()
    page.screenshot(path=ARTIFACTS / f"{mode}-fleet.png", full_page=True)

    # Configure from the fleet list: the badge changes in place, without a reload.
    page.evaluate("window.__sameDocument = true")
    row.get_by_role("button", name=re.compile("^configure")).click()
    expect(row.locator(".row-result")).to_contain_text("configure succeeded", timeout=WAIT_MS)
    expect(row.locator(".badge")).to_have_text("inactive", timeout=WAIT_MS)
    assert page.evaluate("window.__sameDocument") is True

    # Activate from the node page: progress, result, graph and history follow live.
    row.locator("a").click()
    expect(page.locator("h1")).to_contain_text(f"/{node}")
    wait_live(page, WAIT_MS)
    page.get_by_role("button", name="activate", exact=True).click()
    expect(page.locator("#transition-result")).to_contain_text("activate succeeded", timeout=WAIT_MS)
    expect(page.locator("#node-state .badge.big")).to_have_text("active")
    expect(page.locator(".graph svg:visible .state-box.current")).to_contain_text("active")
    expect(page.locator("#audit-rows tr").first).to_contain_text("bruno-operator")
    page.screenshot(path=ARTIFACTS / f"{mode}-node.png", full_page=True)

    # A failing transition shows the node's own reason.
    page.goto(f"{base}nodes/{ROBOT}.flaky_node/")
    wait_live(page, WAIT_MS)
    page.get_by_role("button", name="configure", exact=True).click()
    result = page.locator("#transition-result")
    expect(result).to_contain_text("Failed", timeout=WAIT_MS)
    expect(result).to_contain_text("The node said")
    page.screenshot(path=ARTIFACTS / f"{mode}-node-failed.png", full_page=True)

    # The node's log: history and live lines; the level filter hides INFO.
    page.goto(f"{base}logs/node/{key}/")
    lines = page.locator(".log-line")
    expect(lines.filter(has_text="activated").first).to_be_visible(timeout=WAIT_MS)
    page.select_option("[data-log=level]", "ERROR")
    expect(lines.filter(has_text="activated").first).to_be_hidden()
    page.select_option("[data-log=level]", "DEBUG")
    page.screenshot(path=ARTIFACTS / f"{mode}-logs.png")

    # The audit history has it all, with who did it and from where.
    page.goto(f"{base}audit/?robot={ROBOT}")
    table = page.locator("table.audit")
    expect(table).to_contain_text("bruno-operator")
    expect(table).to_contain_text("dashboard")
    expect(table).to_contain_text("failed")
    page.screenshot(path=ARTIFACTS / f"{mode}-audit.png", full_page=True)
    assert ours.count() - before == 2
    assert page.console_errors == []


def test_state_change_by_another_client_arrives_without_reload(page: Page, base_url, api):
    """A transition made elsewhere (here: the API) shows up on an open fleet page."""
    base, mode = base_url
    log_in(page, base)
    key = f"{ROBOT}.flaky_node"
    badge = page.locator(dom_id(key)).locator(".badge")
    expect(badge).to_have_text("unconfigured", timeout=WAIT_MS)
    page.fill("[data-filter=q]", "flaky")
    expect(page.locator(dom_id(f"{ROBOT}.lidar_driver"))).to_be_hidden()
    response = api.post(f"/api/v1/nodes/{key}/transition", {"transition": "configure"},
                        content_type="application/json")
    assert response.status_code == 422  # fail_configure: the attempt is made, the node refuses
    # Its failure reaches the open page: the node heads "needs attention", with its own words,
    # and its row (still shown under the filter) is marked.
    failed = page.locator(f'#attention li.attention-item[data-key="{key}"]')
    expect(failed).to_contain_text("simulated hardware not found", timeout=WAIT_MS)
    expect(page.locator(dom_id(key))).to_have_attribute("data-attention", re.compile(".+"), timeout=WAIT_MS)
    expect(page.locator(dom_id(key))).to_be_visible()
    assert page.console_errors == []
