"""A node whose process crashes during activate, on its page in a real browser: the answer says
'Process lost' at once (not 'activating' for the service timeout, then 'Timed out'), the state
panel says when, and once a new instance runs the stale message is gone, the panel says
'Process restarted (new instance)' and the parameter table shows the new process's values."""
from __future__ import annotations

import re
import time

import pytest
from playwright.sync_api import Page, expect

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import Robot
from tests import stack
from tests.browser.conftest import ARTIFACTS, submit_login, watched_page
from tests.integration.conftest import register, wait_node

ROBOT = "br-crash"
KEY = f"{ROBOT}.bc.flaky_node"
WAIT_MS = 20_000
BOUND_MS = 3_000  # the tests' service timeout is 3 s: the answer must come before it


def start_flaky(name: str, mode: str) -> stack.Process:
    return stack.start_robot(name, stack.domain(28), "flaky_node", f"flaky_node.failure_mode:={mode}",
                             namespace="/bc")


@pytest.fixture(scope="module")
def crashing(gateway):
    register(ROBOT, stack.domain(28), namespace="/bc")
    processes = [start_flaky("br-crash-1", "crash")]
    wait_node(None, KEY, alive=True, state="unconfigured", timeout=30)
    yield processes
    for process in processes:
        process.stop()
    Robot.objects.filter(name=ROBOT).delete()  # later modules count the fleet's flaky nodes


@pytest.fixture
def page(browser):
    with watched_page(browser, page_errors=True, viewport={"width": 1280, "height": 1000}) as page:
        yield page


def test_a_crash_during_activate_and_the_new_instance_on_the_node_page(page: Page, site, crashing, operator):
    page.goto(f"{site}nodes/{KEY}/")
    submit_login(page, "bruno-operator")
    expect(page.locator("h1")).to_contain_text("/bc/flaky_node", timeout=WAIT_MS)
    value = page.locator("#param-value-failure_mode")
    expect(value).to_have_text("crash", timeout=WAIT_MS)

    page.get_by_role("button", name="configure", exact=True).click()
    result = page.locator("#transition-result")
    expect(result).to_contain_text("configure succeeded", timeout=WAIT_MS)
    expect(page.locator("#node-state .badge.big")).to_have_text("inactive", timeout=WAIT_MS)
    # The next live update of another state clears the old message (here: the crash's).
    clicked = time.monotonic()
    page.get_by_role("button", name="activate", exact=True).click()
    expect(result).to_contain_text("Process lost", timeout=BOUND_MS)
    print(f"[crash-ui] 'Process lost' shown {time.monotonic() - clicked:.2f} s after the click")
    expect(result).to_contain_text("process ended during activate")
    expect(result).not_to_contain_text("Timed out")
    state = page.locator("#node-state")
    expect(state.locator(".badge.big")).to_have_text("lost")
    expect(state).to_contain_text(re.compile(r"Process lost at \d\d:\d\d:\d\d"))
    expect(page.locator("#audit-rows tr.outcome-process_lost")).to_have_count(1, timeout=WAIT_MS)
    page.screenshot(path=ARTIFACTS / "crash-lost.png", full_page=True)
    # The message stays while the node is what it said (lost).
    page.wait_for_timeout(1500)
    expect(result).to_contain_text("Process lost")

    crashing.append(start_flaky("br-crash-2", "none"))  # its supervisor starts it again
    expect(state.locator(".badge.big")).to_have_text("unconfigured", timeout=WAIT_MS)
    expect(state).to_contain_text(re.compile(r"Process restarted \(new instance\) at \d\d:\d\d:\d\d"),
                                  timeout=WAIT_MS)
    expect(result.locator(".result")).to_have_count(0, timeout=WAIT_MS)
    expect(value).to_have_text("none", timeout=WAIT_MS)
    page.screenshot(path=ARTIFACTS / "crash-restarted.png", full_page=True)
    outcomes = set(TransitionRecord.objects.filter(node__key=KEY).values_list("outcome", flat=True))
    assert {"process_lost", "process_restarted"} <= outcomes, outcomes
    assert page.console_errors == [], page.console_errors
