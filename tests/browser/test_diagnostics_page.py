"""A robot's diagnostics at phone size, on real parts: DiagnosticArray publishers of the test (its
/diagnostics and an aggregator's /diagnostics_agg), the gateway, the ingest, daphne and Chromium.
The tree shows the aggregator's hierarchy with badges that carry their level in words; a status
that goes to ERROR changes on the open page without a reload; its own page has its history; the
fleet's needs-attention strip lists it; nothing is wider than the phone."""
from __future__ import annotations

import re

import pytest
from playwright.sync_api import expect

from lifecycle_site.diagnostics.models import Status
from tests import stack
from tests.browser.conftest import ARTIFACTS, PHONE, ROBOT, logged_in_page, wait_live
from tests.integration.diagnostics_publisher import Source

WAIT_MS = 30_000
TREE = ["/BR", "/BR/Sensors", "/BR/Sensors/Lidar", "/BR/Power", "/BR/Power/Battery"]


@pytest.fixture
def aggregator(robot):
    source = Source(stack.domain(7), stack.environment(), "--node", "br_aggregator", "--topic", "diagnostics_agg",
                    "--statuses", "0", "--rate", "2")
    try:
        for name in TREE:
            source.send(name=name, level=0, message="fine", values=[["frequency_hz", "10.0"]])
        stack.wait_for(lambda: Status.objects.filter(robot__name=ROBOT, name__in=TREE).count() == len(TREE), 20,
                       "the aggregated statuses")
        yield source
    finally:
        source.stop()
        Status.objects.filter(robot__name=ROBOT, name__in=TREE).delete()


def test_the_tree_at_phone_size_follows_a_status_to_error_and_to_its_history(browser, site, operator, aggregator):
    with logged_in_page(browser, site, viewport=PHONE, device_scale_factor=1, is_mobile=True,
                        has_touch=True) as page:
        page.goto(f"{site}robots/{ROBOT}/diagnostics/")
        wait_live(page)
        tree = page.locator("#diagnostics-live")
        lidar = tree.locator("li.diag-row.depth-2", has_text="Lidar")
        expect(lidar).to_contain_text("OK")
        expect(lidar.locator(".diag-level")).to_have_text("✓ OK")
        sensors = tree.locator("li.diag-row.depth-1", has_text="Sensors")
        expect(sensors).to_be_visible()

        aggregator.send(name="/BR/Sensors/Lidar", level=2, message="no scans for 3 s",
                        values=[["frequency_hz", "0.0"]])
        expect(lidar.locator(".diag-level")).to_have_text("✕ ERROR", timeout=10_000)  # no reload
        expect(lidar).to_contain_text("no scans for 3 s")
        expect(sensors.locator(".diag-level")).to_have_text("✕ ERROR")  # its branch shows the worst below
        expect(page.locator("#diagnostics-counts")).not_to_contain_text("0 ERROR")
        assert page.evaluate("document.documentElement.scrollWidth") <= PHONE["width"]
        page.screenshot(path=ARTIFACTS / "phone-diagnostics.png", full_page=True)

        lidar.get_by_role("link", name="Lidar").click()
        expect(page.locator("h1")).to_contain_text("/BR/Sensors/Lidar")
        history = page.locator("table.diag-history")
        expect(history).to_contain_text("ERROR")
        expect(history).to_contain_text("no scans for 3 s")
        expect(page.locator("table.diag-values")).to_contain_text("frequency_hz")
        expect(page.locator("svg.diag-lane rect.diag-error")).to_have_count(1)
        assert page.evaluate("document.documentElement.scrollWidth") <= PHONE["width"]

        page.goto(site)
        expect(page.locator("#attention")).to_contain_text("diagnostic ERROR", timeout=WAIT_MS)
        expect(page.locator("#attention")).to_contain_text("/BR/Sensors/Lidar")

        # A status nobody reports any more goes stale, live; an operator forgets it (asked first).
        # The button is there only while a status is stale.
        page.goto(f"{site}robots/{ROBOT}/diagnostics/")
        wait_live(page)
        forget = page.get_by_role("button", name=re.compile("^Forget"))
        expect(forget).to_have_count(0)
        aggregator.send(drop="/BR/Power/Battery")
        battery = page.locator("#diagnostics-live li.diag-row.depth-2", has_text="Battery")
        expect(battery.locator(".diag-level")).to_have_text("? STALE", timeout=30_000)
        expect(forget).to_have_text("Forget 1 stale status")
        forget.click()
        dialog = page.locator("dialog#confirm-dialog")
        expect(dialog).to_contain_text(f"Forget the stale diagnostic statuses of {ROBOT}?")
        dialog.get_by_role("button", name="Cancel").click()
        page.wait_for_timeout(500)
        assert Status.objects.filter(robot__name=ROBOT, name="/BR/Power/Battery").exists()  # cancelled: kept
        forget.click()
        dialog.get_by_role("button", name="Forget them").click()
        expect(page.locator("#diagnostics-forgotten")).to_contain_text("Forgot 1 stale status: /BR/Power/Battery")
        expect(battery).to_have_count(0)
        expect(forget).to_have_count(0)
        assert not Status.objects.filter(robot__name=ROBOT, name="/BR/Power/Battery").exists()
        assert page.console_errors == []
