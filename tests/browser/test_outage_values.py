"""No stale values during a gateway outage (issue 26, item 8), in Chromium on the real stack: the
node page's header says the gateway is offline (not a green "online" under the red banner), the
banner's "N s ago" advances, a red "nothing was sent" goes once the gateway is back, and the log
console marks the stretch of /rosout that was not received.

The gateway of this module is stopped and a replacement started: keep this module on its own."""
from __future__ import annotations

import re

from django.utils import timezone
from playwright.sync_api import Page, expect

from lifecycle_site.fleet.models import GatewayOutage
from tests import stack
from tests.browser.conftest import ARTIFACTS, ROBOT, submit_login
from tests.integration.conftest import wait_node

WAIT_MS = 30_000
KEY = f"{ROBOT}.lidar_driver"
DESKTOP = {"width": 1440, "height": 900}
PHONE = {"width": 390, "height": 844}


def seconds_ago(text: str) -> int:
    found = re.search(r"(\d+) s ago", text)
    assert found, text
    return int(found.group(1))


def test_header_banner_refusal_and_log_gap_follow_the_outage(browser, site, robot, operator, gateway):
    wait_node(None, KEY, alive=True)
    context = browser.new_context(viewport=DESKTOP)
    node_page: Page = context.new_page()
    errors: list[str] = []
    node_page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    node_page.goto(f"{site}nodes/{KEY}/")
    submit_login(node_page, "bruno-operator")
    header = node_page.locator(".node-head .gateway-of")
    expect(header).to_contain_text("online", timeout=WAIT_MS)
    fleet = context.new_page()
    fleet.goto(site)
    expect(fleet.locator("#fleet-live")).to_have_attribute("data-socket", "open", timeout=WAIT_MS)
    logs = context.new_page()
    logs.goto(f"{site}logs/robot/{ROBOT}/")
    expect(logs.locator("[data-log=status]")).to_contain_text("lines shown", timeout=WAIT_MS)
    phone = browser.new_context(viewport=PHONE, is_mobile=True, has_touch=True).new_page()
    phone.goto(f"{site}nodes/{KEY}/")
    submit_login(phone, "bruno-operator")

    stopped = timezone.now()
    assert gateway.stop() == 0
    replacement = None
    try:
        banner = node_page.locator("#gateway-banner")
        expect(banner).to_be_visible(timeout=20_000)
        expect(header.locator(".badge")).to_have_text("offline", timeout=10_000)
        expect(header).not_to_contain_text("online")
        first = seconds_ago(banner.inner_text())
        node_page.wait_for_timeout(12_000)
        later = seconds_ago(banner.inner_text())
        assert later >= first + 10, (first, later)  # it advances with the clock
        node_page.screenshot(path=ARTIFACTS / "outage-node-desktop.png", full_page=False)
        expect(phone.locator(".node-head .gateway-of .badge")).to_have_text("offline", timeout=10_000)
        phone.screenshot(path=ARTIFACTS / "outage-node-phone.png", full_page=False)

        # The robot's group operations are disabled, saying why (as its rows' transitions).
        bring_up = fleet.locator(f"#robot-{ROBOT}").get_by_role("button", name="Bring up", exact=True)
        expect(bring_up).to_be_disabled(timeout=10_000)
        expect(bring_up).to_have_attribute("title", re.compile("gateway is offline"))
        # One clicked in the moment before the page learned of it is refused in red: nothing was sent.
        bring_up.evaluate("(button) => { button.disabled = false; button.click(); }")
        refusal = fleet.locator(f"#robot-{ROBOT}-run-result")
        expect(refusal).to_contain_text("nothing was sent", timeout=WAIT_MS)

        replacement = stack.start_gateway()
        expect(banner).to_be_hidden(timeout=30_000)
        expect(header.locator(".badge")).to_have_text("online", timeout=10_000)
        # Back: the red refusal goes (it spoke of a gateway that is offline no more), and no panel
        # of a run that never started says it instead.
        expect(refusal).not_to_contain_text("nothing was sent", timeout=15_000)
        fleet.wait_for_timeout(4_000)  # the socket's next look at the runs
        expect(fleet.locator(f"#robot-{ROBOT}")).not_to_contain_text("nothing was sent")
        fleet.screenshot(path=ARTIFACTS / "outage-fleet-back.png", full_page=False)
        # The log console marks the stretch whose /rosout was not received.
        outage = stack.wait_for(lambda: GatewayOutage.objects.filter(gateway__name="local", ended__gte=stopped).first(),
                                20, "the outage on record")
        gap = logs.locator(f'.log-lines .log-gap[data-gap="{outage.id}"]')
        expect(gap).to_have_count(1, timeout=20_000)
        expect(gap).to_contain_text("gateway local")
        expect(gap).to_contain_text(re.compile(r"\d\d:\d\d:\d\d.*\d\d:\d\d:\d\d"))  # from, to
        expect(gap).to_contain_text("not received")
        logs.screenshot(path=ARTIFACTS / "outage-log-gap.png", full_page=False)
        logs.reload()  # a console opened later shows it too
        expect(gap).to_have_count(1, timeout=WAIT_MS)
        assert not [e for e in errors if "error" in e.lower()], errors
    finally:
        if replacement is not None:
            replacement.stop()
        phone.context.close()
        context.close()
