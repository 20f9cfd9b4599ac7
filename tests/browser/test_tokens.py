"""API tokens made and revoked in a real browser, used against the real site process."""
from __future__ import annotations

import urllib.error
import urllib.request

from playwright.sync_api import expect

from lifecycle_site.api.models import TokenEvent
from tests.browser.conftest import ROBOT, submit_login

WAIT_MS = 20_000


def api_status(site: str, token: str) -> int:
    request = urllib.request.Request(site + "api/v1/robots", headers={"Authorization": f"Bearer {token}"})
    try:
        with urllib.request.urlopen(request, timeout=20) as answer:
            return answer.status
    except urllib.error.HTTPError as exc:
        return exc.code


def test_an_operator_makes_a_token_on_a_phone_uses_it_and_revokes_it(browser, site, robot, operator):
    context = browser.new_context(viewport={"width": 390, "height": 844}, is_mobile=True)
    page = context.new_page()
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.goto(site + "login/")
    submit_login(page, "bruno-operator")
    expect(page.locator("h2", has_text=ROBOT)).to_be_visible(timeout=WAIT_MS)

    page.goto(site + "tokens/")
    page.get_by_label("What is it for?").fill("line 3 bring-up script")
    page.get_by_role("button", name="Make a token").click()
    shown = page.get_by_role("textbox", name="New token")
    expect(shown).to_be_visible(timeout=WAIT_MS)
    token = shown.input_value()
    assert token.startswith("lcm_") and len(token) > 40
    expect(page.locator(".token-once")).to_contain_text("shown only this once")
    assert page.evaluate("document.documentElement.scrollWidth") <= 390
    assert api_status(site, token) == 200

    page.goto(site + "tokens/")  # shown once: not again
    assert token not in page.content()
    row = page.locator("tr", has_text="line 3 bring-up script")
    expect(row).to_contain_text(token[:10])
    row.get_by_role("button", name="Revoke").click()
    expect(page.locator(".messages")).to_contain_text("revoked: it no longer works", timeout=WAIT_MS)
    assert api_status(site, token) == 401
    assert list(TokenEvent.objects.filter(hint=token[:10]).values_list("action", "actor_name")) == [
        ("revoked", "bruno-operator"), ("created", "bruno-operator")]
    assert errors == []
    context.close()
