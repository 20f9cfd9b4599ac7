"""Live panels you can trust: a run panel says the run's own policy and reaches its final
state on every page that shows it (a restart on the node page, a recovery the gateway started
by itself), runs survive a reload, and pages without robots say nothing of gateways."""
from __future__ import annotations

import re
import signal

from playwright.sync_api import expect

from lifecycle_site.fleet.models import GroupRun, ManagedNode, Robot
from tests import stack
from tests.browser.conftest import ARTIFACTS, COUNT_LIVE, ROBOT, submit_login, wait_live
from tests.conftest import make_user
from tests.integration.conftest import wait_node

WAIT_MS = 30_000




def _login(browser, site, user="bruno-operator", **viewport):
    context = browser.new_context(viewport=viewport or {"width": 1280, "height": 900})
    context.add_init_script(COUNT_LIVE)
    page = context.new_page()
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.goto(site + "login/")
    submit_login(page, user)
    return page, errors


def live(page, url: str) -> None:
    """Open ``url`` and wait for its live socket's first message (the snapshot on connect)."""
    page.goto(url)
    wait_live(page, WAIT_MS)


def test_group_run_panel_says_its_own_policy(browser, site, robot, operator):
    page, errors = _login(browser, site)
    live(page, site)
    section = page.locator(f"#robot-{ROBOT}")
    section.locator("select[name=policy]").select_option("stop")
    section.get_by_role("button", name="Pause").click()  # nothing to pause: a quick run
    run = section.locator(".run").first
    expect(run).to_contain_text("succeeded", timeout=WAIT_MS)
    # No bring-up order is set for this robot: its nodes run side by side (test_run_panels.py).
    expect(run).to_contain_text("after a failure it starts no further node")
    expect(run).not_to_contain_text("continues past failures")
    assert errors == []
    page.context.close()


def test_restart_on_the_node_page_reaches_its_final_state(browser, site, robot, operator):
    page, errors = _login(browser, site)
    live(page, f"{site}nodes/{ROBOT}.lidar_driver/")
    page.get_by_role("button", name="Restart (back to active)").click()
    page.locator("dialog#confirm-dialog").get_by_role("button", name="Restart").click()
    run = page.locator("#node-run .run").first
    expect(run).to_contain_text("Restart", timeout=WAIT_MS)
    expect(run.locator(".run-status")).to_have_text("succeeded", timeout=WAIT_MS)
    expect(run).not_to_contain_text("working…")
    page.screenshot(path=ARTIFACTS / "node-restart-finished.png", full_page=True)
    # Reloaded, the page still shows the run it just made, finished.
    page.reload()
    expect(page.locator("#node-run .run").first.locator(".run-status")).to_have_text("succeeded")
    assert errors == []
    page.context.close()


def test_recovery_run_shows_live_and_after_a_reload(browser, site, robot, operator):
    register_key = f"{ROBOT}.planner"
    process = stack.start_robot("br-planner-1", stack.domain(7), "planner", extra=("--autostart", "activate"))
    try:
        wait_node(None, register_key, alive=True, state="active", timeout=30)
        Robot.objects.filter(name=ROBOT).update(auto_recover=True)
        node = ManagedNode.objects.get(key=register_key)
        node.desired_state = "active"
        node.save(update_fields=["desired_state"])  # publishes the gateway's config
        page, errors = _login(browser, site)
        live(page, site)
        node_page = page.context.new_page()
        node_page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        live(node_page, f"{site}nodes/{register_key}/")

        process.stop(signal.SIGKILL)  # a crash; its supervisor starts it again
        process = stack.start_robot("br-planner-2", stack.domain(7), "planner")
        recovery = page.locator(f"#robot-{ROBOT}-run .run", has_text="Recovery").first
        expect(recovery.locator(".run-status")).to_have_text("succeeded", timeout=WAIT_MS)
        expect(recovery).to_contain_text("/planner")
        on_node_page = node_page.locator("#node-run .run", has_text="Recovery").first
        expect(on_node_page.locator(".run-status")).to_have_text("succeeded", timeout=WAIT_MS)
        page.screenshot(path=ARTIFACTS / "fleet-recovery.png", full_page=True)

        page.reload()  # the run and its result are still there
        expect(page.locator(f"#robot-{ROBOT}-run .run", has_text="Recovery").first).to_contain_text("succeeded")
        assert not [e for e in errors if "oobErrorNoTarget" in e or "error" in e.lower()], errors
        node_page.close()
        page.context.close()
    finally:
        Robot.objects.filter(name=ROBOT).update(auto_recover=False)
        ManagedNode.objects.filter(key=register_key).update(desired_state="")
        process.stop()


def test_a_run_started_elsewhere_appears_with_its_final_state(browser, site, robot, operator, api):
    """A run made by the API (or another screen) while the page is open shows up and ends."""
    page, errors = _login(browser, site)
    live(page, site)
    response = api.post(f"/api/v1/robots/{ROBOT}/operations", {"operation": "pause", "policy": "continue"},
                        content_type="application/json")
    assert response.status_code in (200, 201, 202), response.content
    run_id = GroupRun.objects.filter(robot__name=ROBOT).order_by("-created").values_list("id", flat=True).first()
    panel = page.locator(f"#run-{run_id}")
    # Over (the planner of the recovery test is gone by now: that node fails, the others pass).
    expect(panel.locator(".run-status")).to_have_text(re.compile("^(succeeded|partial|failed)$"), timeout=WAIT_MS)
    expect(panel).to_contain_text("continues past failures")
    assert errors == []
    page.context.close()


def test_pages_without_robots_say_nothing_of_an_offline_gateway(browser, site, robot, operator, live_db):
    page, errors = _login(browser, site)
    page.goto(site + "audit/")
    expect(page.locator("h1")).to_have_text("Audit history")
    page.wait_for_timeout(4_000)  # a live page would have had its first gateway check by now
    expect(page.locator("#gateway-banner")).to_be_hidden()
    # (Records of commands refused by an offline gateway, of earlier modules, say it in the table.)
    outside_tables = page.locator(":not(table *)")
    expect(page.locator("main").get_by_text("is offline").and_(outside_tables)).to_have_count(0)
    page.context.close()

    make_user("nora-norole", None)
    page, errors = _login(browser, site, user="nora-norole")
    expect(page.locator("h1")).to_contain_text("no role")
    page.wait_for_timeout(4_000)
    expect(page.locator("#gateway-banner")).to_be_hidden()
    expect(page.get_by_text("is offline")).to_have_count(0)
    page.context.close()


def test_rows_say_last_known_and_take_no_command_while_the_gateway_is_offline(browser, site, robot, operator,
                                                                              gateway):
    """Last in this module: it stops the module's gateway (a replacement runs afterwards)."""
    key = f"{ROBOT}.camera_driver"
    wait_node(None, key, alive=True)
    page, errors = _login(browser, site)
    row = page.locator("#node-" + key.replace(".", "__"))
    expect(row.locator(".seen")).to_contain_text("running", timeout=WAIT_MS)
    expect(row.get_by_role("button").first).to_be_enabled()
    node_page = page.context.new_page()
    live(node_page, f"{site}nodes/{key}/")
    restart = node_page.get_by_role("button", name="Restart (back to active)")
    expect(restart).to_be_enabled()

    assert gateway.stop() == 0
    replacement = None
    try:
        expect(node_page.locator("#gateway-banner")).to_be_visible(timeout=20_000)
        expect(restart).to_be_disabled(timeout=10_000)
        expect(node_page.locator("#node-restart")).to_contain_text("gateway local is offline")
        state = node_page.locator("#node-state")  # pushed: the state is last known, with its age
        expect(state).to_contain_text("Last known state, as of", timeout=10_000)
        expect(state.locator("span.meta", has_text="Last known state").locator("[data-age]")).to_contain_text("ago")
        expect(page.locator("#gateway-banner")).to_be_visible(timeout=20_000)
        expect(row.locator(".seen")).not_to_contain_text("running", timeout=10_000)
        expect(row.locator(".seen")).to_contain_text("last known")
        buttons = row.locator(".actions button")
        assert buttons.count() > 0
        for i in range(buttons.count()):
            expect(buttons.nth(i)).to_be_disabled()
        group = page.locator(f"#robot-{ROBOT} form.operations").get_by_role("button", name="Bring up")
        expect(group).to_be_disabled()  # the robot's group operations as well
        page.screenshot(path=ARTIFACTS / "fleet-gateway-offline-rows.png", full_page=True)

        replacement = stack.start_gateway()
        expect(page.locator("#gateway-banner")).to_be_hidden(timeout=30_000)
        expect(row.locator(".seen")).to_contain_text("running", timeout=20_000)
        expect(row.get_by_role("button").first).to_be_enabled()
        expect(group).to_be_enabled()
        expect(restart).to_be_enabled(timeout=20_000)
    finally:
        if replacement is not None:
            replacement.stop()
        page.context.close()
