"""The node page's socket snapshot and a transition's result, in Chromium on the real stack. The
snapshot is read as the socket opens; a click answered before it arrives is newer than it, and
its result must stay (seen in CI: a snapshot read before the transition was stored deleted the
result). A result shown before the socket (re)opened is older than the snapshot, which clears it
when the node has moved on meanwhile. Playwright's WebSocket routing holds the server's messages
back to make each order happen every time."""
from __future__ import annotations

import re
import subprocess
import sys

from playwright.sync_api import expect

from lifecycle_site.fleet.models import ManagedNode
from ros_gateway.shared import state_machine as sm
from tests import stack
from tests.browser.conftest import DESKTOP, ROBOT, sized_page, wait_live

WAIT_MS = 20_000
NODE = "camera_driver"
KEY = f"{ROBOT}.{NODE}"


class HeldSocket:
    """Routes the node page's socket through the test: while ``holding``, what the server sends is
    kept back (in order) until ``release``."""

    def __init__(self, page) -> None:
        self.holding, self.held, self.route = True, [], None
        page.route_web_socket(re.compile(r".*/ws/nodes/.*"), self._connect)

    def _connect(self, route) -> None:
        self.route = route
        server = route.connect_to_server()  # the page's messages go on to the server as they are
        server.on_message(lambda message: self.held.append(message) if self.holding else route.send(message))

    def wait_held(self, page) -> None:
        """Until the server has sent something (held back)."""
        for _ in range(200):
            if self.held:
                return
            page.wait_for_timeout(100)
        raise AssertionError("the node page's socket sent nothing within 20 s")

    def release(self) -> None:
        self.holding = False
        for message in self.held:
            self.route.send(message)
        self.held.clear()


def state_badge(page):
    return page.locator("#node-state .badge.big")


def reconnect(page) -> None:
    """What htmx does after an abnormal close, at once (its own delay is random)."""
    page.evaluate("document.querySelector('[ws-connect]')['htmx-internal-data'].webSocket.init()")


def test_a_result_newer_than_the_sockets_snapshot_stays_an_older_one_goes_once_the_node_moved_on(
        browser, site, robot, operator):
    assert ManagedNode.objects.get(key=KEY).state_label == "unconfigured"
    page = sized_page(browser, site, DESKTOP)
    try:
        held = HeldSocket(page)
        page.goto(f"{site}nodes/{KEY}/")
        held.wait_held(page)  # the snapshot (unconfigured), read before the click below
        page.click("#node-state button[data-transition=configure]")
        result = page.locator("#transition-result .result")
        expect(result).to_contain_text("Done", timeout=WAIT_MS)
        held.release()  # the snapshot, then the live update of the new state
        wait_live(page, WAIT_MS)
        expect(state_badge(page)).to_have_text("inactive", timeout=WAIT_MS)
        expect(result).to_contain_text("Done")  # newer than the snapshot: kept

        # The socket drops; meanwhile another tool activates the node; the page reconnects.
        held.holding = True
        held.route.close(code=1000)  # (htmx does not reconnect on its own after a normal close)
        done = subprocess.run([sys.executable, "tests/integration/ros_call.py", str(stack.domain(7)), f"/{NODE}",
                               str(sm.ACTIVATE)], env=stack.environment(), capture_output=True, text=True, timeout=30)
        assert "success" in done.stdout, done.stdout + done.stderr
        stack.wait_for(lambda: ManagedNode.objects.get(key=KEY).state_label == "active", 20, "the node stored active")
        reconnect(page)
        held.wait_held(page)
        expect(page.locator("#transition-result .result[data-before-socket]")).to_have_count(1)  # shown before
        held.release()  # the snapshot (active): the configure's result is about a state left since
        expect(state_badge(page)).to_have_text("active", timeout=WAIT_MS)
        expect(result).to_have_count(0, timeout=WAIT_MS)
    finally:
        page.context.close()
