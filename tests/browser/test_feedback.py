"""Feedback where the operator looks: a row's button answers in that row (robot and node named,
on a phone too), clears itself and keeps the keyboard there; irreversible actions ask first,
impossible ones are not offered; watching a node by name works in the page; a reconnect keeps
the choices made in the forms."""
from __future__ import annotations

import re

import pytest
from django.test import Client
from playwright.sync_api import expect

from lifecycle_site.fleet.models import GroupRun, ManagedNode, Robot
from tests import stack
from tests.browser.conftest import ARTIFACTS, COUNT_LIVE, submit_login, wait_live
from tests.integration.conftest import register, transition, wait_node

WAIT_MS = 30_000
OTHER = "br-agv2"  # a second robot that also has a /camera_driver
KEY = f"{OTHER}.camera_driver"


def dom(key: str) -> str:
    return "#node-" + key.replace(".", "__")


@pytest.fixture(scope="module")
def other_robot(robot):
    from django.utils import timezone

    started = timezone.now()
    # A domain of its own: a robot of another module registered for the whole of a shared
    # domain (it-ops, domain 8) would take its node if the gateway saw the node first.
    register(OTHER, stack.domain(32))
    process = stack.start_robot("br2-nodes", stack.domain(32), "camera_driver")
    try:
        wait_node(None, KEY, alive=True, state="unconfigured", seen_since=started, timeout=30)
        yield process
    finally:
        process.stop()
        Robot.objects.filter(name=OTHER).delete()  # later modules see the fleet of br-agv alone


def open_fleet(browser, site, **viewport):
    context = browser.new_context(viewport=viewport or {"width": 1280, "height": 900})
    context.add_init_script(COUNT_LIVE)
    page = context.new_page()
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type in ("error", "warning") else None)
    page.goto(site + "login/")
    submit_login(page, "bruno-operator")
    wait_live(page, WAIT_MS)
    return page, errors


def test_a_row_answers_in_the_row_naming_robot_and_node_and_keeps_the_focus(browser, site, other_robot, operator):
    page, errors = open_fleet(browser, site, width=390, height=844)  # a phone
    row = page.locator(dom(KEY))
    button = row.get_by_role("button", name=re.compile("^configure"))
    button.focus()
    page.keyboard.press("Enter")
    answer = row.locator(".row-result .result")
    expect(answer).to_contain_text(f"{OTHER} /camera_driver", timeout=WAIT_MS)
    expect(answer).to_be_in_viewport()
    expect(row.locator(".badge")).to_have_text("inactive", timeout=WAIT_MS)  # the row was redrawn live
    expect(answer).to_contain_text("configure")  # the answer outlived the redraw
    page.screenshot(path=ARTIFACTS / "phone-row-answer.png")
    focused_row = page.evaluate("(document.activeElement.closest('tr') || {}).id || null")
    assert focused_row == dom(KEY)[1:], focused_row
    for _ in range(4):  # the next step, from where the keyboard is: activate, a Tab or two away
        if page.evaluate("document.activeElement.dataset.transition") == "activate":
            break
        page.keyboard.press("Tab")
    page.keyboard.press("Enter")
    expect(row.locator(".badge")).to_have_text("active", timeout=WAIT_MS)
    expect(row.locator(".row-result .result")).to_have_count(0, timeout=20_000)  # it cleared itself
    assert errors == []
    page.context.close()


def test_watch_a_node_by_name_in_the_page(browser, site, other_robot, operator):
    page, errors = open_fleet(browser, site)
    page.evaluate("window.__sameDocument = true")
    section = page.locator(f"#robot-{OTHER}")
    field = section.locator("form.watch input[name=name]")
    field.fill("/not_started_yet")
    assert field.evaluate("el => el.checkValidity()") is True
    field.fill("/bad name")
    assert field.evaluate("el => el.checkValidity()") is False  # the browser checks the pattern
    field.fill("/not_started_yet")
    section.get_by_role("button", name="Watch").click()
    expect(section.locator("form.watch")).to_contain_text("Watching /not_started_yet", timeout=WAIT_MS)
    waiting = page.locator(dom(f"{OTHER}.not_started_yet"))
    expect(waiting.locator(".badge")).to_have_text("waiting")
    assert page.evaluate("window.__sameDocument") is True  # no reload
    assert not [e for e in errors if "pattern" in e.lower()], errors

    # A name not started yet does not stop a bring-up with the "stop" policy.
    section.locator("select[name=policy]").select_option("stop")
    section.get_by_role("button", name="Bring up").click()
    run = section.locator(".run").first
    expect(run.locator(".run-status")).to_have_text("succeeded", timeout=WAIT_MS)
    expect(run).not_to_contain_text("not_started_yet")
    stack.wait_for(lambda: GroupRun.objects.filter(robot__name=OTHER).first().status == "succeeded", 15,
                   "the bring-up to be stored as succeeded")

    # It can be unwatched here, not only in the admin.
    waiting.get_by_role("button", name=re.compile("Stop watching")).click()
    expect(waiting).to_have_count(0, timeout=WAIT_MS)
    assert not ManagedNode.objects.filter(key=f"{OTHER}.not_started_yet").exists()
    assert page.evaluate("window.__sameDocument") is True
    page.context.close()


def test_shutdown_asks_first_and_a_finalized_node_offers_no_restart(browser, site, other_robot, operator, api):
    for step in ("configure", "activate"):  # active, whatever the tests before left
        if ManagedNode.objects.get(key=KEY).state_label != "active":
            transition(api, KEY, step)
    wait_node(None, KEY, alive=True, state="active")
    page, errors = open_fleet(browser, site)
    row = page.locator(dom(KEY))
    dialog = page.locator("dialog#confirm-dialog")  # the page's own (test_confirm.py)

    row.get_by_role("button", name=re.compile("^shutdown")).click()
    expect(dialog).to_contain_text("finalized")
    dialog.get_by_role("button", name="Cancel").click()
    page.wait_for_timeout(2_000)
    assert ManagedNode.objects.get(key=KEY).state_label == "active"  # nothing was sent

    page.goto(f"{site}nodes/{KEY}/")  # the node page asks too
    page.locator("#node-state").get_by_role("button", name="shutdown").click()
    expect(dialog).to_contain_text("finalized")
    page.keyboard.press("Escape")
    page.wait_for_timeout(2_000)
    assert ManagedNode.objects.get(key=KEY).state_label == "active"
    page.goto(site)
    wait_live(page, WAIT_MS)

    row.get_by_role("button", name=re.compile("^shutdown")).click()
    dialog.get_by_role("button", name="Shut down").click()
    expect(row.locator(".badge")).to_have_text("finalized", timeout=WAIT_MS)
    expect(row.locator(".seen")).not_to_contain_text("running")
    expect(row.locator(".seen")).to_contain_text("restart its process")

    page.goto(f"{site}nodes/{KEY}/")
    restart = page.get_by_role("button", name="Restart (back to active)")
    expect(restart).to_be_disabled()
    expect(page.locator("#node-restart")).to_contain_text("finalized")
    page.screenshot(path=ARTIFACTS / "node-finalized-restart.png", full_page=True)
    client = Client()
    client.force_login(operator)
    refused = client.post(f"/nodes/{KEY}/restart", HTTP_HX_REQUEST="true")
    assert b"finalized" in refused.content
    assert not GroupRun.objects.filter(robot__name=OTHER, operation="restart").exists()
    page.context.close()


def test_a_reconnect_keeps_the_choices_made_in_the_forms(browser, site, robot, operator):
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    context.add_init_script(COUNT_LIVE)
    page = context.new_page()
    sockets = []

    def relay(ws):
        ws.connect_to_server()
        sockets.append(ws)

    page.route_web_socket(re.compile(r"/ws/fleet/$"), relay)
    page.goto(site + "login/")
    submit_login(page, "bruno-operator")
    wait_live(page, WAIT_MS)
    section = page.locator("#robot-br-agv")
    section.locator("select[name=policy]").select_option("continue")
    section.locator("input[name=timeout]").fill("7")
    # The answer to the last click stays too (it was wiped when a snapshot came after it).
    Robot.objects.filter(name="br-agv").update(enabled=False)
    try:
        section.get_by_role("button", name="Bring up", exact=True).click()
        expect(page.locator("#robot-br-agv-run-result")).to_contain_text("is disabled", timeout=WAIT_MS)
    finally:
        Robot.objects.filter(name="br-agv").update(enabled=True)
    page.evaluate("document.getElementById('robots').dataset.before = 'reconnect'")
    sockets[-1].close(code=1012, reason="restarting")  # the site restarted: htmx reconnects
    expect(page.locator("#robots[data-before]")).to_have_count(0, timeout=WAIT_MS)
    assert len(sockets) >= 2
    expect(section.locator("select[name=policy]")).to_have_value("continue")
    expect(section.locator("input[name=timeout]")).to_have_value("7")
    expect(page.locator("#robot-br-agv-run-result")).to_contain_text("is disabled")
    context.close()
