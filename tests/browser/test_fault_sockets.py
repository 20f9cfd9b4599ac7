"""Live-update sockets when the site loses Redis and gets it back: a page says what happened
and is live again by itself (no reload, nothing restarted); handshakes while Redis is down
are refused with a code the page retries on, not HTTP 500; and once Redis is back every
handshake succeeds, also those that draw a connection the channel layer pooled before the
restart (8 of 50 failed with HTTP 500 a minute and a half after Redis was back)."""
from __future__ import annotations

import asyncio
import time
from collections import Counter
from urllib.parse import urlparse

from playwright.sync_api import expect
from websockets.exceptions import ConnectionClosed, InvalidStatus

from lifecycle_site.dashboard.consumers import TRY_AGAIN_LATER
from lifecycle_site.gateway_link import gateways
from tests import stack
from tests.benchmarks.web import Http, ws_connect
from tests.browser.conftest import PASSWORD, ROBOT, submit_login
from tests.integration.conftest import node_state, transition

SOCKETS = 50


async def handshake(web: Http) -> str:
    """Open the fleet socket and read its first message: "ok", "closed CODE" or "http STATUS"."""
    try:
        async with ws_connect(web, "/ws/fleet/") as ws:
            await asyncio.wait_for(ws.recv(), 20)
            return "ok"
    except InvalidStatus as exc:
        return f"http {exc.response.status_code}"
    except ConnectionClosed as exc:
        return f"closed {exc.rcvd.code if exc.rcvd else None}"


async def handshakes(web: Http, count: int) -> Counter:
    return Counter(await asyncio.gather(*(handshake(web) for _ in range(count))))


def local_online() -> bool:
    gateways.forget()
    return gateways.status("local").online


def test_handshakes_are_refused_cleanly_without_redis_and_all_succeed_once_it_is_back(site, robot, operator,
                                                                                      redis_server):
    address = urlparse(site)
    web = Http(address.hostname, address.port)
    web.login(operator.username, PASSWORD)
    try:
        # Many at once: the channel layer of daphne pools a connection for each.
        assert asyncio.run(handshakes(web, SOCKETS)) == Counter({"ok": SOCKETS})
        redis_server.stop()
        try:
            refused = asyncio.run(handshakes(web, 5))
        finally:
            redis_server.start()
        assert refused == Counter({f"closed {TRY_AGAIN_LATER}": 5}), refused
        back = time.monotonic()
        outcomes = asyncio.run(handshakes(web, SOCKETS))
        assert outcomes == Counter({"ok": SOCKETS}), f"{outcomes} {time.monotonic() - back:.1f} s after Redis was back"
    finally:
        web.close()


def test_an_open_page_says_it_lost_redis_and_is_live_again_by_itself(browser, site, robot, operator, redis_server,
                                                                       api):
    page = browser.new_page(viewport={"width": 1024, "height": 768})
    try:
        page.goto(site + "login/")
        submit_login(page, operator.username)
        expect(page.locator("h2", has_text=ROBOT)).to_be_visible(timeout=20_000)
        page.wait_for_timeout(1000)  # the live socket is open
        banner = page.locator("#ws-banner")
        redis_server.stop()
        try:
            expect(banner).to_contain_text("lost its link to Redis", timeout=20_000)
            expect(banner).to_be_visible()
        finally:
            redis_server.start()
        back = time.monotonic()
        expect(banner).to_be_hidden(timeout=20_000)
        reconnected = time.monotonic() - back
        # Live again: a change made elsewhere shows on the page.
        stack.wait_for(local_online, 30, "the gateway online after Redis came back")
        key = f"{ROBOT}.camera_driver"
        state = node_state(api, key)["state"]["label"]
        step, after = {"unconfigured": ("configure", "inactive"), "inactive": ("cleanup", "unconfigured"),
                       "active": ("deactivate", "inactive")}[state]
        assert transition(api, key, step).status_code == 200
        badge = page.locator("#node-" + key.replace(".", "__")).locator(".badge")
        expect(badge).to_have_text(after, timeout=15_000)
        assert reconnected < 20, reconnected
    finally:
        page.close()
