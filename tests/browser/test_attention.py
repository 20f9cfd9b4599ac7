"""The fleet page leads with what needs attention (issue 26, item 2), in Chromium on the real stack:
a node whose transition just failed no longer looks like a healthy one. A strip at the top lists,
worst first, each problem with the node's own reason and a link; its row is marked; the state
filter offers "needs attention"; the page title carries the count; all of it follows live."""
from __future__ import annotations

import re

import pytest
from playwright.sync_api import Page, expect

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import Gateway, ManagedNode, Robot
from lifecycle_site.gateway_link import gateways, quarantine
from tests import stack
from tests.browser.conftest import ARTIFACTS, DESKTOP, PHONE, ROBOT, sized_page
from tests.integration.conftest import transition, wait_node

WAIT_MS = 30_000
FLAKY, LIDAR, CAMERA = f"{ROBOT}.flaky_node", f"{ROBOT}.lidar_driver", f"{ROBOT}.camera_driver"
CUT_OFF = "br-cell-q"  # a gateway that never runs here, quarantined by the site
CUT_OFF_REASON = "its Redis keys held 70 MB, over their quota of 64 MB"


def dom(key: str) -> str:
    return "#node-" + key.replace(".", "__")


def open_fleet(browser, site: str, viewport: dict) -> Page:
    page = sized_page(browser, site, viewport)
    expect(page.locator("#fleet-live")).to_have_attribute("data-socket", "open", timeout=WAIT_MS)
    return page


def title_says_the_count(page: Page, strip) -> None:
    """The tab's title counts what the strip lists now (other items than the test's own, such as a
    robot process restarted by an earlier test, may come or go meanwhile)."""
    def same() -> bool:
        count = len(strip.locator("li.attention-item").all())
        counted = strip.get_attribute("data-count") == str(count)
        return count > 0 and counted and page.title().startswith(f"{count} need")

    stack.wait_for(same, WAIT_MS / 1000, "the title to count the strip's items")


def set_mode(api, mode: str) -> None:
    answer = api.patch(f"/api/v1/nodes/{FLAKY}/parameters", {"failure_mode": mode}, content_type="application/json")
    assert answer.status_code == 200, answer.content


def last_failure(key: str) -> TransitionRecord:
    return stack.wait_for(lambda: TransitionRecord.objects.filter(node__key=key).exclude(outcome="succeeded").first(),
                          15, f"a failed record of {key}")


@pytest.fixture
def cut_off_gateway(robot, live_db):
    """A second gateway with a robot, quarantined (its keys over their quota)."""
    row = Gateway.objects.create(name=CUT_OFF, redis_password_sha256="0" * 64)
    Robot.objects.create(name="br-q", domain_id=stack.domain(9), gateway=row)
    quarantine.quarantine(CUT_OFF, CUT_OFF_REASON)
    yield row
    quarantine.lift(row)
    Robot.objects.filter(name="br-q").delete()
    row.delete()  # and its Redis user (gateway_link/redis_users.py)
    gateways.forget_beats()


def test_problems_lead_the_fleet_page_worst_first_marked_filtered_counted_and_live(
        browser, site, robot, operator, api, cut_off_gateway):
    wait_node(None, FLAKY, alive=True, state="unconfigured")
    transition(api, FLAKY, "configure")  # failure_mode=fail_configure: it stays unconfigured
    failure = last_failure(FLAKY)
    assert "simulated hardware not found" in failure.error, failure.error
    ManagedNode.objects.filter(key=LIDAR).update(desired_state="active")  # it is unconfigured
    # Robots of earlier modules set aside (their failures would fill the strip's places).
    others = list(Robot.objects.exclude(name__in=[ROBOT, "br-q"]).filter(enabled=True).values_list("pk", flat=True))
    Robot.objects.filter(pk__in=others).update(enabled=False)
    try:
        page = open_fleet(browser, site, DESKTOP)
        strip = page.locator("#attention")
        items = strip.locator("li.attention-item")
        flaky = strip.locator("li.attention-item", has=page.locator(f'a[href$="/nodes/{FLAKY}/"]'))
        expect(flaky).to_contain_text("/flaky_node", timeout=WAIT_MS)
        expect(flaky).to_contain_text("configure failed")
        expect(flaky).to_contain_text("simulated hardware not found on /dev/ttyFLAKY")  # the node's own words
        # Worst first: the gateway cut off (it takes its robots with it), the failed transition,
        # then the node not in its desired state.
        texts = items.all_inner_texts()
        gateway = next(i for i, t in enumerate(texts) if CUT_OFF in t)
        failed = next(i for i, t in enumerate(texts) if f"{ROBOT} /flaky_node" in t)
        lidar = next(i for i, t in enumerate(texts) if f"{ROBOT} /lidar_driver" in t)
        assert gateway < failed < lidar, texts
        assert "desired state active" in texts[lidar], texts[lidar]
        assert "quarantined" in texts[gateway] and "70 MB" in texts[gateway], texts[gateway]
        count = int(strip.get_attribute("data-count"))
        expect(page).to_have_title(re.compile(rf"^{count} need attention · Fleet"))
        # Each affected row carries a marker; a healthy one does not.
        expect(page.locator(dom(FLAKY)).locator(".attention-mark")).to_be_visible()
        expect(page.locator(dom(LIDAR)).locator(".attention-mark")).to_be_visible()
        expect(page.locator(dom(CAMERA)).locator(".attention-mark")).to_have_count(0)
        page.screenshot(path=ARTIFACTS / "fleet-attention-desktop.png", full_page=True)

        # The state filter: only the rows that need attention.
        page.select_option("select[data-filter=state]", "attention")
        shown = page.locator(f"#robot-{ROBOT} tr.node-row:visible")
        expect(shown).to_have_count(2)
        assert sorted(shown.evaluate_all("rows => rows.map(r => r.dataset.name)")) == ["/flaky_node", "/lidar_driver"]
        page.select_option("select[data-filter=state]", "")

        # On a phone the strip is the first thing under the filters, readable, not wider than the screen.
        phone = open_fleet(browser, site, PHONE)
        expect(phone.locator("#attention li.attention-item").first).to_be_in_viewport(timeout=WAIT_MS)
        assert phone.evaluate("document.documentElement.scrollWidth") <= PHONE["width"]
        phone.screenshot(path=ARTIFACTS / "fleet-attention-phone.png", full_page=False)
        assert phone.console_errors == []
        phone.context.close()

        # Live: fixed, the node leaves the strip and loses its marker ...
        set_mode(api, "none")
        assert transition(api, FLAKY, "configure").status_code == 200
        expect(strip).not_to_contain_text("/flaky_node", timeout=15_000)
        expect(page.locator(dom(FLAKY)).locator(".attention-mark")).to_have_count(0)
        title_says_the_count(page, strip)
        # ... and an activation that fails brings it back, with that failure's reason.
        set_mode(api, "raise_activate")
        transition(api, FLAKY, "activate")
        expect(flaky).to_contain_text("activate failed", timeout=15_000)
        expect(flaky).to_contain_text("simulated driver fault while activating")
        expect(page.locator(dom(FLAKY)).locator(".attention-mark")).to_be_visible()
        title_says_the_count(page, strip)
        page.screenshot(path=ARTIFACTS / "fleet-attention-live.png", full_page=True)
        assert page.console_errors == []
        page.context.close()
    finally:
        ManagedNode.objects.filter(key=LIDAR).update(desired_state="")
        Robot.objects.filter(pk__in=others).update(enabled=True)
        set_mode(api, "fail_configure")


def test_behind_a_proxy_the_strip_links_under_its_prefix_also_when_sent_live(browser, proxied_site, robot, operator,
                                                                            api):
    page = open_fleet(browser, proxied_site, DESKTOP)
    strip = page.locator("#attention")
    try:
        ManagedNode.objects.filter(key=CAMERA).update(desired_state="active")  # it is unconfigured: sent live
        item = strip.locator("li.attention-item", has_text="/camera_driver")
        expect(item).to_be_visible(timeout=15_000)
        expect(item.get_by_role("link")).to_have_attribute("href", f"/lifecycle/nodes/{CAMERA}/")
        item.get_by_role("link").click()
        expect(page).to_have_url(re.compile(rf"/lifecycle/nodes/{re.escape(CAMERA)}/$"))
        assert page.console_errors == []
    finally:
        ManagedNode.objects.filter(key=CAMERA).update(desired_state="")
        page.context.close()
