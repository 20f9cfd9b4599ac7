"""The fleet page of a large fleet in Chromium, on the real stack: robots beyond the size the site
is told to show whole (here a fleet of more than 10 nodes, robots of more than 8, instead of 300
and 25) show their counts by state; any of their nodes is reachable by the name filter and in two
clicks; an opened robot stays open on reload; live updates keep the counts and opened rows current."""
from __future__ import annotations

import re
import sys

import pytest
from playwright.sync_api import expect

from lifecycle_site.fleet.models import Robot
from tests import stack
from tests.browser.conftest import ARTIFACTS, submit_login
from tests.integration.conftest import register, wait_node

BIG = {"bs-big-1": 27, "bs-big-2": 28}  # robot -> offset of its ROS domain
PER_ROBOT = 12


def prefix(robot: str) -> str:
    return robot.replace("-", "_").replace("bs_big_", "bsb")


@pytest.fixture(scope="module")
def big_robots(gateway):
    from django.utils import timezone

    started = timezone.now()
    processes = []
    for robot, offset in BIG.items():
        register(robot, stack.domain(offset))
        processes.append(stack.start_robot(f"{robot}-nodes", stack.domain(offset), "",
                                           extra=("--generic", str(PER_ROBOT), "--generic-prefix", prefix(robot))))
    try:
        for robot in BIG:
            for i in range(PER_ROBOT):
                wait_node(None, f"{robot}.{prefix(robot)}_{i:03d}", timeout=90, alive=True, state="unconfigured",
                          seen_since=started)
        yield processes
    finally:
        for process in processes:
            process.stop()
        Robot.objects.filter(name__in=list(BIG)).delete()  # later modules see the fleet without them


@pytest.fixture(scope="module")
def small_site(gateway):
    """daphne told to collapse robots of more than 8 nodes in a fleet of more than 10."""
    port = stack.free_port()
    process = stack.Process(
        "daphne-fleet-scale",
        [sys.executable, "-m", "lifecycle_site.serve", "-b", "127.0.0.1", "-p", str(port),
         "lifecycle_site.asgi:application"],
        stack.environment(LIFECYCLE_FLEET_COLLAPSE_ABOVE="10", LIFECYCLE_ROBOT_COLLAPSE_ABOVE="8"),
        stack.log_dir(),
    )
    stack.wait_for(lambda: stack.listens(port) or not process.alive(), 30, "daphne to listen")
    assert process.alive(), process.output()
    yield f"http://127.0.0.1:{port}/"
    process.stop()


def transition(api, key: str, name: str) -> None:
    answer = api.post(f"/api/v1/nodes/{key}/transition", {"transition": name}, content_type="application/json")
    assert answer.status_code == 200, answer.content


def test_a_node_of_a_collapsed_robot_is_found_by_filter_and_in_two_clicks(browser, small_site, big_robots,
                                                                          operator, api):
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    try:
        page.goto(small_site + "login/")
        submit_login(page, "bruno-operator")
        one, two = page.locator("#robot-bs-big-1"), page.locator("#robot-bs-big-2")
        expect(one).to_have_attribute("data-collapsed", "true", timeout=20_000)
        expect(two).to_have_attribute("data-collapsed", "true")
        expect(one.locator(".robot-summary")).to_contain_text(f"{PER_ROBOT} unconfigured")
        assert one.locator("tr.node-row").count() == 0
        expect(page.locator("#fleet-live")).to_have_attribute("data-socket", "open", timeout=15_000)

        # Live: a node of the collapsed robot changes state; its counts follow, no row comes.
        transition(api, "bs-big-1.bsb1_003", "configure")
        expect(one.locator(".robot-summary")).to_contain_text(f"{PER_ROBOT - 1} unconfigured", timeout=15_000)
        expect(one.locator(".robot-summary")).to_contain_text("1 inactive")
        assert one.locator("tr.node-row").count() == 0

        # By filter: the name box lists the matches in collapsed robots; one click opens the node.
        page.fill("input[data-filter=q]", "bsb1_007")
        match = page.locator("#fleet-matches a", has_text="/bsb1_007")
        expect(match).to_be_visible(timeout=10_000)
        page.screenshot(path=ARTIFACTS / "fleet-scale-filter.png")
        match.click()
        expect(page).to_have_url(re.compile(r"/nodes/bs-big-1\.bsb1_007/$"))

        # In two clicks: open the robot, then the node.
        page.goto(small_site)
        expect(two).to_have_attribute("data-collapsed", "true", timeout=20_000)
        expect(page.locator("#fleet-live")).to_have_attribute("data-socket", "open", timeout=15_000)
        two.get_by_role("button", name=f"Show the {PER_ROBOT} nodes of bs-big-2").click()
        expect(two.locator("tr.node-row")).to_have_count(PER_ROBOT, timeout=10_000)
        expect(page).to_have_url(re.compile(r"[?&]open=bs-big-2"))
        # Live rows of the opened robot (the socket was told it is open).
        transition(api, "bs-big-2.bsb2_005", "configure")
        row = page.locator("#node-bs-big-2__bsb2_005")
        expect(row.locator(".badge")).to_have_text("inactive", timeout=15_000)
        page.screenshot(path=ARTIFACTS / "fleet-scale-opened.png")
        row.get_by_role("link", name="/bsb2_005").click()
        expect(page).to_have_url(re.compile(r"/nodes/bs-big-2\.bsb2_005/$"))

        # Back on the fleet page (a reload of its URL), the robot is still open.
        page.go_back()
        page.reload()
        expect(two.locator("tr.node-row")).to_have_count(PER_ROBOT, timeout=20_000)
        expect(one).to_have_attribute("data-collapsed", "true")
    finally:
        for key, name in (("bs-big-1.bsb1_003", "cleanup"), ("bs-big-2.bsb2_005", "cleanup")):
            try:
                transition(api, key, name)
            except AssertionError:
                pass
        page.close()
