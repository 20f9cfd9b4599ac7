"""The Content-Security-Policy in a real Chromium: every page (the admin's included) works under
it without a single violation, htmx still does its work (transitions, live updates, lazy
panels), and a script injected into a page does not run."""
from __future__ import annotations

import re

import pytest
from django.contrib.auth import get_user_model
from playwright.sync_api import Page, expect

from lifecycle_site.fleet.models import Robot
from tests.browser.conftest import ARTIFACTS, PASSWORD, ROBOT, submit_login

WAIT_MS = 20_000
# Reports every violation to the test, whatever page the browser is on (init scripts and
# bindings come from the browser's debugging protocol: the page's policy does not apply to them).
REPORT_VIOLATIONS = """document.addEventListener("securitypolicyviolation", function (e) {
  window.cspViolation(e.violatedDirective + " blocked " + (e.blockedURI || "?") + " in " + e.sourceFile + ":" +
                      e.lineNumber);
});"""


@pytest.fixture
def page(browser):
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    context.violations, context.errors = [], []
    context.expose_binding("cspViolation", lambda _source, text: context.violations.append(text))
    context.add_init_script(REPORT_VIOLATIONS)
    page = context.new_page()
    page.on("console", lambda m: m.type == "error" and context.errors.append(f"{m.text} ({m.location.get('url')})"))
    page.on("pageerror", lambda e: context.errors.append(str(e)))
    yield page
    context.close()


@pytest.fixture(scope="module")
def superuser(live_db):
    user = get_user_model().objects.filter(username="csp-root").first() or get_user_model().objects.create_superuser(
        "csp-root", "", PASSWORD)
    return user


def visit(page: Page, url: str) -> None:
    """Open ``url``; its answer must carry the policy."""
    answer = page.goto(url)
    assert answer is not None and answer.ok, (url, answer and answer.status)
    assert "script-src 'self'" in answer.headers.get("content-security-policy", ""), (url, answer.headers)


def assert_clean(page: Page) -> None:
    page.wait_for_timeout(300)  # a late violation report reaches the binding
    assert page.context.violations == [], page.context.violations
    assert page.context.errors == [], page.context.errors


def test_the_dashboard_works_under_the_policy(page: Page, site, robot, operator):
    key = f"{ROBOT}.lidar_driver"
    visit(page, site + "login/")
    submit_login(page, "bruno-operator")
    expect(page.locator("h2", has_text=ROBOT)).to_be_visible(timeout=WAIT_MS)

    visit(page, site)
    row = page.locator("#node-" + key.replace(".", "__"))
    expect(row.locator(".badge")).to_have_text("unconfigured", timeout=WAIT_MS)
    page.evaluate("window.__sameDocument = true")
    # htmx: a transition button (hx-post, hx-vals, the CSRF header), its answer and the live push.
    row.get_by_role("button", name=re.compile("^configure")).click()
    expect(row.locator(".row-result")).to_contain_text("configure succeeded", timeout=WAIT_MS)
    expect(row.locator(".badge")).to_have_text("inactive", timeout=WAIT_MS)
    page.fill("input[data-filter=q]", "lidar")
    page.press("input[data-filter=q]", "Enter")  # filters in the page: no reload (was an inline handler)
    expect(page.locator(".fleet-total")).to_contain_text("of")
    assert page.evaluate("window.__sameDocument") is True
    assert_clean(page)

    visit(page, f"{site}nodes/{key}/")
    expect(page.locator("#parameters table")).to_be_visible(timeout=WAIT_MS)  # hx-trigger="load"
    page.get_by_role("button", name="activate", exact=True).click()
    expect(page.locator("#transition-result")).to_contain_text("activate succeeded", timeout=WAIT_MS)
    expect(page.locator("#node-state .badge.big")).to_have_text("active")
    expect(page.locator(".htmx-indicator")).to_be_hidden()  # site.css, not htmx's own <style>
    expect(page.locator("#audit-rows tr").first).to_contain_text("bruno-operator")
    assert_clean(page)

    visit(page, f"{site}logs/node/{key}/")
    expect(page.locator("[data-log=status]")).to_contain_text("lines shown", timeout=WAIT_MS)
    page.evaluate("window.__sameDocument = true")
    page.press("[data-log=text]", "Enter")
    assert page.evaluate("window.__sameDocument") is True
    assert_clean(page)

    for timeline in (f"nodes/{key}/timeline/?window=week", f"robots/{ROBOT}/timeline/"):
        visit(page, site + timeline)
        expect(page.locator("figure.timeline svg.tl-svg")).to_be_visible(timeout=WAIT_MS)  # not role=img: has links
        assert_clean(page)

    visit(page, f"{site}audit/")
    expect(page.locator("table.audit tbody tr").first).to_contain_text("bruno-operator")
    page.screenshot(path=ARTIFACTS / "csp-audit.png", full_page=True)
    assert_clean(page)

    # What the policy is for: script that found its way into a page does not run, be it a
    # <script> element, an on* attribute or code in an htmx attribute.
    page.evaluate("""() => {
        const s = document.createElement("script");
        s.textContent = "window.__injected = 'script'";
        document.body.appendChild(s);
        document.body.insertAdjacentHTML("beforeend",
            '<button id="inj-onclick" onclick="window.__injected = \\'onclick\\'">a</button>' +
            '<button id="inj-htmx" hx-on:click="window.__injected = \\'hx-on\\'">b</button>');
        htmx.process(document.getElementById("inj-htmx"));
    }""")
    page.click("#inj-onclick")
    page.click("#inj-htmx")
    page.wait_for_timeout(300)
    assert page.evaluate("window.__injected === undefined"), page.evaluate("window.__injected")
    blocked = [v for v in page.context.violations if v.startswith("script-src")]
    assert any(" inline " in v for v in blocked) and len(blocked) >= 2, page.context.violations


def test_the_admin_works_under_the_policy(page: Page, site, robot, superuser):
    visit(page, site + "admin/login/")
    page.fill("#id_username", "csp-root")
    page.fill("#id_password", PASSWORD)
    page.click("input[type=submit]")
    expect(page.locator("#site-name")).to_be_visible(timeout=WAIT_MS)
    robot_id = Robot.objects.get(name=ROBOT).pk
    for path in ("", "fleet/robot/", "fleet/robot/add/", f"fleet/robot/{robot_id}/change/", "fleet/gateway/",
                 "auth/user/add/", "auth/group/add/", "audit/accessdenial/", "audit/transitionrecord/",
                 "axes/accessattempt/"):
        visit(page, f"{site}admin/{path}")
        expect(page.locator("#content")).to_be_visible()
    assert_clean(page)

    # The admin's own scripts ran: the two-list group picker, the inline rows, the action counter.
    visit(page, f"{site}admin/auth/user/{superuser.pk}/change/")
    expect(page.locator(".selector").first).to_be_visible()  # SelectFilter2.js built it
    visit(page, f"{site}admin/fleet/robot/{robot_id}/change/")
    expect(page.locator(".add-row a")).to_contain_text("Add another")  # inlines.js added it
    page.screenshot(path=ARTIFACTS / "csp-admin-robot.png", full_page=True)
    visit(page, f"{site}admin/fleet/robot/")
    page.check("#action-toggle")
    expect(page.locator(".action-counter")).to_contain_text("selected")
    assert_clean(page)
