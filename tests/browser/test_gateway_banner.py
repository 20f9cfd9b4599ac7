"""The page says when the gateway is gone, and recovers by itself when it is back."""
from __future__ import annotations

from playwright.sync_api import expect

from tests import stack
from tests.browser.conftest import ARTIFACTS, ROBOT, submit_login


def test_gateway_offline_banner_comes_and_goes(browser, site, robot, operator, gateway):
    page = browser.new_page(viewport={"width": 1024, "height": 768})
    page.goto(site + "login/")
    submit_login(page, "bruno-operator")
    banner = page.locator("#gateway-banner")
    expect(page.locator("h2", has_text=ROBOT)).to_be_visible(timeout=20_000)
    expect(banner).to_be_hidden()

    assert gateway.stop() == 0
    expect(banner).to_be_visible(timeout=15_000)
    expect(banner).to_contain_text("gateway local is offline")
    page.screenshot(path=ARTIFACTS / "gateway-offline.png")

    replacement = stack.start_gateway()
    try:
        expect(banner).to_be_hidden(timeout=20_000)
        badge = page.locator("#node-" + f"{ROBOT}.lidar_driver".replace(".", "__")).locator(".badge")
        expect(badge).not_to_have_text("lost", timeout=20_000)
    finally:
        replacement.stop()
        page.close()
