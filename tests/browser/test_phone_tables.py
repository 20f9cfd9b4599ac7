"""Every table on a phone (issue 26, item 3): one card per row, each value labelled with its
column's heading, nothing off-screen (the alerts' Acknowledge button included); on a desktop
still a table whose headings sit over their cells. Alert rows link to the node, its logs and
its timeline."""
from __future__ import annotations

import pytest
from playwright.sync_api import Page, expect

from lifecycle_site.alerts.models import Alert, Rule
from lifecycle_site.api.models import ApiToken
from lifecycle_site.fleet.models import Robot
from tests import stack
from tests.browser.conftest import ARTIFACTS, ROBOT, live_page, logged_in_page
from tests.integration.conftest import transition, wait_node

WAIT_MS = 30_000
PHONE = {"width": 390, "height": 844}
DESKTOP = {"width": 1440, "height": 900}
KEY = f"{ROBOT}.camera_driver"
FLAKY = f"{ROBOT}.flaky_node"
# The pages and the table on each (with rows in it, made by the fixture below).
TABLES = {
    "alerts": ("alerts/", "table.alerts"),
    "audit": (f"audit/?robot={ROBOT}", "table.audit"),
    "parameter-audit": (f"audit/?kind=parameters&robot={ROBOT}", "table.audit"),
    "node-history": (f"nodes/{KEY}/", "table.audit"),
    "tokens": ("tokens/", "table.tokens"),
}
# Each row's cells: [visible?, its ::before label, its left and right edge], and the headings.
CELLS = """(table) => ({
  headings: Array.from(table.querySelectorAll('thead th')).map((th) => th.textContent.trim()),
  rows: Array.from(table.querySelectorAll('tbody tr')).filter((tr) => tr.getClientRects().length).map((tr) =>
    Array.from(tr.children).map((td) => {
      const box = td.getBoundingClientRect();
      const label = getComputedStyle(td, '::before').content;
      return {shown: td.getClientRects().length > 0 && getComputedStyle(td).display !== 'none',
              label: label === 'none' || label === 'normal' ? '' : JSON.parse(label),
              text: td.textContent.trim(), left: box.left, right: box.right, top: box.top};
    })),
  headingShown: Array.from(table.querySelectorAll('thead th')).map((th) => getComputedStyle(th).display !== 'none'
    && th.getClientRects().length > 0),
})"""


@pytest.fixture(scope="module")
def records(robot, operator, api):
    """A transition that succeeded, one that failed (with the node's reason), a parameter
    change, a firing alert and an API token: a row in each table."""
    from tests.integration.conftest import node_state

    state = node_state(api, KEY)["state"]["label"]
    step = {"unconfigured": "configure", "inactive": "cleanup", "active": "deactivate"}[state]
    assert transition(api, KEY, step).status_code == 200
    transition(api, f"{ROBOT}.flaky_node", "configure")  # fail_configure: refused, with its reason
    changed = api.patch(f"/api/v1/nodes/{KEY}/parameters", {"fps": 12.0}, content_type="application/json")
    assert changed.status_code == 200
    wait_node(api, KEY, alive=True)
    # flaky_node stays unconfigured (fail_configure): the rule's alert fires and stays firing.
    rule = Rule.objects.create(name="br-phone-tables", kind=Rule.Kind.STATE, state="unconfigured",
                               robot=Robot.objects.get(name=ROBOT), node_pattern="/flaky_node")
    stack.wait_for(lambda: Alert.objects.filter(rule=rule, status="firing").first(), 20, "the alert to fire")
    alert = Alert.objects.get(rule=rule)
    ApiToken.issue(operator, "phone tables")
    yield alert
    rule.delete()
    Alert.objects.filter(rule_name="br-phone-tables").delete()


@pytest.fixture
def phone(browser, site, records):
    with logged_in_page(browser, site, viewport=PHONE, device_scale_factor=1, is_mobile=True, has_touch=True) as page:
        yield page


@pytest.fixture
def desktop(browser, site, records):
    with logged_in_page(browser, site, viewport=DESKTOP) as page:
        yield page


def read_table(page: Page, site: str, name: str) -> dict:
    path, selector = TABLES[name]
    page.goto(site + path)
    table = page.locator(selector)
    expect(table.locator("tbody tr").first).to_be_visible(timeout=WAIT_MS)
    return table.evaluate(CELLS)


@pytest.mark.parametrize("name", TABLES)
def test_on_a_phone_each_row_is_a_card_with_every_value_labelled(phone: Page, site, name):
    page = phone
    table = read_table(page, site, name)
    page.screenshot(path=ARTIFACTS / f"phone-table-{name}.png", full_page=True)
    assert page.evaluate("document.documentElement.scrollWidth") <= PHONE["width"], "the page scrolls sideways"
    assert not any(table["headingShown"]), "headings over columns that are not there"
    headings = table["headings"]
    for row in table["rows"]:
        if len(row) == 1:  # "No ... yet": one cell over the whole width
            continue
        assert len(row) == len(headings), row
        for heading, cell in zip(headings, row, strict=True):
            if not cell["shown"]:
                continue
            assert cell["right"] <= PHONE["width"], f"{heading or 'a cell'} is off-screen: {cell}"
            if heading and cell["text"]:
                assert cell["label"] == heading, f"{cell['text']!r} is labelled {cell['label']!r}, not {heading!r}"
        shown = [c for c in row if c["shown"] and c["text"]]
        assert len({round(c["top"]) for c in shown}) == len(shown), "cells side by side: not a card"
    if name == "alerts":  # the operator can reach the button
        button = page.get_by_role("button", name="Acknowledge")
        button.scroll_into_view_if_needed()
        box = button.bounding_box()
        assert box and box["x"] >= 0 and box["x"] + box["width"] <= PHONE["width"] and box["height"] >= 44


@pytest.mark.parametrize("name", TABLES)
def test_on_a_desktop_tables_stay_tables_with_headings_over_their_cells(desktop: Page, site, name):
    page = desktop
    table = read_table(page, site, name)
    assert all(table["headingShown"])
    for row in table["rows"]:
        if len(row) == 1:
            continue
        assert all(c["shown"] for c in row)
        assert len({round(c["top"]) for c in row}) == 1, "a desktop row is one line of cells"
        assert all(not c["label"] for c in row)
    if name == "alerts":
        page.screenshot(path=ARTIFACTS / "desktop-table-alerts.png")


def test_an_alert_row_links_to_the_node_its_logs_and_its_timeline(phone: Page, site, records):
    page = phone
    page.goto(site + "alerts/")
    row = page.locator(f"#alert-{records.id}")
    links = {name: row.get_by_role("link", name=name, exact=True) for name in ("/flaky_node", "Logs", "Timeline")}
    assert links["/flaky_node"].get_attribute("href").endswith(f"/nodes/{FLAKY}/")
    assert links["Logs"].get_attribute("href").endswith(f"/logs/node/{FLAKY}/")
    assert links["Timeline"].get_attribute("href").endswith(f"/nodes/{FLAKY}/timeline/")
    assert all(link.bounding_box()["height"] >= 44 for link in links.values())  # a finger's size
    page.screenshot(path=ARTIFACTS / "phone-alert-links.png")
    links["Timeline"].tap()
    expect(page.locator("h1")).to_contain_text("State timeline")
    page.go_back()
    row.get_by_role("link", name="/flaky_node", exact=True).tap()
    expect(page.locator("h1")).to_contain_text("/flaky_node")


def test_the_fleet_on_a_phone_fits_with_every_node_cell_shown(phone: Page, site):
    """The fleet's rows on a phone: name and state, then the buttons, then when it was seen
    (hidden before, with the 4th heading of every other table)."""
    page = phone
    live_page(page, site)  # the socket's snapshot redraws the rows: a row found before is gone after
    rows = page.locator("tr.node-row")
    expect(rows.first).to_be_visible(timeout=WAIT_MS)
    assert page.evaluate("document.documentElement.scrollWidth") <= PHONE["width"]
    # Found and measured in one go: a live update may redraw the row at any time.
    cells = page.evaluate("""() => Array.from(document.querySelector('tr.node-row').children).map((td) => {
      const box = td.getBoundingClientRect(); return [td.getClientRects().length > 0, box.left, box.right]; })""")
    assert all(shown and left >= 0 and right <= PHONE["width"] for shown, left, right in cells), cells
    expect(rows.first.locator("td.seen")).to_be_visible()
    page.screenshot(path=ARTIFACTS / "phone-fleet.png", full_page=True)
