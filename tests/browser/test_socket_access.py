"""A live-update socket stops when its user may no longer see the fleet: after logout, after
the account is deactivated, after its role is removed; a page of another origin cannot open
one. Real daphne, Redis and gateway; the sockets carry a session from the login form, as a
browser's do."""
from __future__ import annotations

import asyncio
import threading
import time
from contextlib import contextmanager
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Iterator
from urllib.parse import urlparse

import pytest
from django.contrib.auth.models import Group
from websockets.exceptions import ConnectionClosed

from lifecycle_site.audit.models import AccessDenial
from tests.benchmarks.web import Http, ws_connect
from tests.browser.conftest import PASSWORD, ROBOT, submit_login
from tests.conftest import make_user

BOUND_S = 5.0  # consumers re-check access every 3 s


def logged_in(site: str, username: str) -> Http:
    address = urlparse(site)
    web = Http(address.hostname, address.port)
    user = make_user(username, "operator")
    user.set_password(PASSWORD)
    user.is_active = True
    user.save()
    web.login(username, PASSWORD)
    return web


def log_out(web: Http) -> None:
    answer = web.request("POST", "/logout/", b"", {"X-CSRFToken": web.cookies["csrftoken"],
                                                   "Content-Type": "application/x-www-form-urlencoded"})
    assert answer.status in (200, 302), answer.status


def revoke(how: str, username: str, web: Http) -> None:
    user = make_user(username, None)
    if how == "logout":
        log_out(web)
    elif how == "deactivated":
        user.is_active = False
        user.save()
    else:
        user.groups.remove(Group.objects.get(name="operator"))


async def closed_after(web: Http, bystander: Http, act) -> tuple[int | None, float, bool]:
    """Open a fleet socket for each, act, return the first one's close code and delay, and
    whether the bystander's socket is still open."""
    async with ws_connect(web, "/ws/fleet/") as ws, ws_connect(bystander, "/ws/fleet/") as other:
        await asyncio.sleep(0.5)
        await asyncio.to_thread(act)
        acted = time.monotonic()
        try:
            while True:
                await asyncio.wait_for(ws.recv(), BOUND_S + 2 - (time.monotonic() - acted))
        except ConnectionClosed:
            pass
        except TimeoutError:
            return None, time.monotonic() - acted, other.close_code is None
        return ws.close_code, time.monotonic() - acted, other.close_code is None


@pytest.mark.parametrize("how, code", [("logout", 4401), ("deactivated", 4401), ("role removed", 4403)])
def test_the_socket_closes_within_seconds_when_access_ends(site, robot, how, code):
    username = f"sock-{how.replace(' ', '-')}"
    web, bystander = logged_in(site, username), logged_in(site, "sock-bystander")
    try:
        outcome = asyncio.run(closed_after(web, bystander, lambda: revoke(how, username, web)))
    finally:
        web.close()
        bystander.close()
    close_code, after, bystander_open = outcome
    assert close_code == code, f"{how}: socket close code {close_code} after {after:.1f} s"
    assert after < BOUND_S, f"{how}: closed after {after:.1f} s"
    assert bystander_open, "another user's socket was closed too"


def test_an_open_page_follows_when_its_users_access_ends(browser, site, robot):
    from playwright.sync_api import expect

    user = make_user("sock-page", "operator")
    user.set_password(PASSWORD)
    user.save()
    page = browser.new_page()
    try:
        page.goto(site + "login/")
        submit_login(page, "sock-page")
        expect(page.locator("h2", has_text=ROBOT)).to_be_visible(timeout=20_000)
        page.wait_for_timeout(1000)  # the live socket is open
        user.groups.clear()
        expect(page.locator("h1")).to_have_text("Your account has no role yet", timeout=BOUND_S * 1000 + 2000)
        user.is_active = False
        user.save()
        page.goto(site)
        expect(page.locator("#id_username")).to_be_visible()  # logged out: the login form
    finally:
        page.close()


ATTACK_PAGE = """<!doctype html><title>another site</title><script>
window.result = {opened: false, messages: [], closed: false};
const socket = new WebSocket("ws://127.0.0.1:%(port)d/ws/fleet/");
socket.onopen = () => { window.result.opened = true; };
socket.onmessage = (event) => { window.result.messages.push(String(event.data).slice(0, 200)); };
socket.onclose = () => { window.result.closed = true; };
</script>"""


@contextmanager
def page_server(html: str) -> Iterator[str]:
    """Another program on the same host serving its own page (another port: another origin)."""

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 (http.server's name)
            body = html.encode()
            self.send_response(200)
            self.send_header("Content-Type", "text/html; charset=utf-8")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/"
    finally:
        server.shutdown()
        server.server_close()
        thread.join(5)


def test_a_page_of_another_origin_cannot_open_the_socket_with_the_users_cookie(browser, site, robot):
    """The browser sends the session cookie of 127.0.0.1 with a socket opened by a page on
    127.0.0.1:<other port> (cookies are per host, not per port): the site refuses it."""
    from playwright.sync_api import expect

    user = make_user("sock-victim", "operator")
    user.set_password(PASSWORD)
    user.save()
    context = browser.new_context()
    page = context.new_page()
    try:
        page.goto(site + "login/")
        submit_login(page, "sock-victim")
        expect(page.locator("h2", has_text=ROBOT)).to_be_visible(timeout=20_000)
        before = AccessDenial.objects.filter(code="socket_origin").count()
        with page_server(ATTACK_PAGE % {"port": urlparse(site).port}) as attacker:
            page.goto(attacker)
            page.wait_for_function("window.result && (window.result.closed || window.result.messages.length)",
                                   timeout=15_000)
            result = page.evaluate("window.result")
    finally:
        context.close()
    assert not result["opened"] and not result["messages"], f"the other origin's page read the fleet: {result}"
    denial = AccessDenial.objects.filter(code="socket_origin").order_by("-id").first()
    assert AccessDenial.objects.filter(code="socket_origin").count() == before + 1
    assert denial.username == "sock-victim" and denial.path == "/ws/fleet/", denial  # the cookie came along
    assert attacker.rstrip("/") in denial.detail, denial.detail
