"""The header's alert count, the alerts page and its Acknowledge button in Chromium, on the real
stack: a lifecycle node shut down to finalized through the API raises the alert."""
from __future__ import annotations

from playwright.sync_api import expect

from lifecycle_site.alerts.models import Alert, Rule
from lifecycle_site.fleet.models import Robot
from tests.browser.conftest import ARTIFACTS, ROBOT, submit_login
from tests.integration.conftest import transition, wait_node

KEY = f"{ROBOT}.camera_driver"


def test_header_count_list_and_acknowledge(browser, site, robot, operator, api):
    rule = Rule.objects.create(name="br-finalized", kind=Rule.Kind.STATE, state="finalized",
                               robot=Robot.objects.get(name=ROBOT), node_pattern="/camera_driver")
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    refused = []
    page.on("console", lambda message: refused.append(message.text) if "Content Security Policy" in message.text
            else None)
    try:
        page.goto(site + "login/")
        submit_login(page, "bruno-operator")
        count = page.locator("#alert-count")
        expect(count.locator(".count")).to_have_text("0", timeout=20_000)

        assert transition(api, KEY, "shutdown").status_code == 200
        wait_node(api, KEY, state="finalized")
        expect(count.locator(".count")).to_have_text("1", timeout=15_000)  # the next poll
        expect(count).to_have_class("alert-count firing")
        count.click()
        alert = Alert.objects.get(rule=rule)
        row = page.locator(f"#alert-{alert.id}")
        expect(row).to_contain_text("Node /camera_driver on robot br-agv is finalized.")
        expect(row.locator(".alert-status")).to_have_text("firing")
        page.screenshot(path=ARTIFACTS / "alerts-firing.png")

        row.get_by_role("button", name="Acknowledge").click()
        expect(row.locator(".alert-status")).to_have_text("acknowledged", timeout=10_000)
        expect(row).to_contain_text("by bruno-operator")
        expect(row.get_by_role("button", name="Acknowledge")).to_have_count(0)
        expect(count.locator(".count")).to_have_text("0", timeout=5_000)  # told at once, not at the next poll
        page.screenshot(path=ARTIFACTS / "alerts-acknowledged.png")
        alert.refresh_from_db()
        assert (alert.status, alert.acknowledged_by_name) == ("acknowledged", "bruno-operator")
        assert refused == []
    finally:
        page.close()
        rule.delete()
        Alert.objects.filter(rule_name="br-finalized").delete()
