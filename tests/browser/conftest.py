"""Browser tests: Debian's Chromium driven by Playwright against the real stack (daphne,
gateway, Redis, rclpy nodes), once directly and once behind an nginx that serves the app
under /lifecycle/ the way an Industrial Edge device does."""
from __future__ import annotations

import os
import sys
import textwrap
from contextlib import contextmanager
from pathlib import Path

import pytest
from django.conf import settings
from playwright.sync_api import expect

from lifecycle_site.fleet.models import ManagedNode
from tests import stack
from tests.conftest import make_user
from tests.integration.conftest import register, wait_node  # noqa: F401 (fixtures)

# Playwright's sync API keeps an event loop running in this thread; the ORM calls the tests
# make are plain blocking calls from it, which Django would otherwise refuse.
os.environ["DJANGO_ALLOW_ASYNC_UNSAFE"] = "true"

ARTIFACTS = stack.ROOT / "tests" / "artifacts"
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
    "--disable-component-update", "--no-first-run", "--disable-sync", "--disable-quic",
]
PASSWORD = "a-test-password-123"
# Counts the live messages a page has swapped in (an init script: it runs before the page's own).
COUNT_LIVE = ("document.addEventListener('htmx:wsAfterMessage', () => "
              "{ document.documentElement.dataset.live = Number(document.documentElement.dataset.live || 0) + 1; });")
ROBOT = "br-agv"


def submit_login(page, username: str, password: str = PASSWORD) -> None:
    """Fill in and send the site's login form, open on ``page``."""
    page.fill("#id_username", username)
    page.fill("#id_password", password)
    page.click("main form button[type=submit]")  # (the header's language choice has buttons too)


DESKTOP = {"width": 1440, "height": 900}
PHONE = {"width": 390, "height": 844}


def sized_page(browser, site: str, viewport: dict, path: str = "", username: str = "bruno-operator"):
    """A page at ``viewport`` (PHONE: a touch-screen phone), logged in as ``username`` on the way
    to ``path``; errors on its console are kept in ``page.console_errors``. Close its context."""
    context = browser.new_context(viewport=viewport, device_scale_factor=1,
                                  **({"is_mobile": True, "has_touch": True} if viewport == PHONE else {}))
    context.add_init_script(COUNT_LIVE)
    page = context.new_page()
    page.console_errors = []
    page.on("console", lambda m: page.console_errors.append(m.text) if m.type == "error" else None)
    page.goto(site + path)
    submit_login(page, username)
    return page


@contextmanager
def watched_page(browser, page_errors: bool = False, **context_options):
    """A page in a browser context of its own; errors on its console (and, with
    ``page_errors``, uncaught script errors) are kept in ``page.console_errors``."""
    context = browser.new_context(**{"viewport": {"width": 1280, "height": 900}, **context_options})
    page = context.new_page()
    page.console_errors = []
    page.on("console", lambda m: page.console_errors.append(m.text) if m.type == "error" else None)
    if page_errors:
        page.on("pageerror", lambda e: page.console_errors.append(str(e)))
    try:
        yield page
    finally:
        context.close()


@contextmanager
def logged_in_page(browser, site: str, username: str = "bruno-operator", **context_options):
    """A watched page logged in as ``username`` and showing the fleet page, once its socket's
    first message (the snapshot) has redrawn it: an element found before may be gone after."""
    with watched_page(browser, **context_options) as page:
        page.context.add_init_script(COUNT_LIVE)
        page.goto(site + "login/")
        submit_login(page, username)
        expect(page.locator("h2", has_text=ROBOT)).to_be_visible(timeout=20_000)
        wait_live(page)
        yield page


def wait_live(page, timeout_ms: int = 30_000) -> None:
    """Wait (on a page with COUNT_LIVE) for its socket's snapshot, which redraws it (the fleet's
    robots, forms included; the node page's state panel): an element found before may be gone
    after, and a click before it may be answered before a snapshot read earlier arrives."""
    expect(page.locator("html[data-live]")).to_have_count(1, timeout=timeout_ms)


def live_page(page, url: str, timeout_ms: int = 30_000) -> None:
    """Open ``url`` and wait for its socket's snapshot (wait_live)."""
    page.goto(url)
    wait_live(page, timeout_ms)


def pytest_collection_modifyitems(items):
    for item in items:
        if "/browser/" in str(item.fspath):
            item.add_marker(pytest.mark.browser)


@pytest.fixture(scope="module")
def robot(gateway):  # noqa: F811
    from django.utils import timezone

    started = timezone.now()
    register(ROBOT, stack.domain(7))
    processes = [
        stack.start_robot("br-nodes", stack.domain(7), "lidar_driver,camera_driver,joystick"),
        stack.start_robot("br-flaky", stack.domain(7), "flaky_node", "flaky_node.failure_mode:=fail_configure"),
    ]
    for node in ("lidar_driver", "camera_driver", "flaky_node"):  # found by this gateway, state read
        wait_node(None, f"{ROBOT}.{node}", alive=True, state="unconfigured", seen_since=started)
    # Nodes an earlier module started on this robot and stopped (a planner) are gone for good:
    # left listed, they would fail this module's robot-wide runs and fill its needs-attention list.
    ManagedNode.objects.filter(robot__name=ROBOT, alive=False).delete()
    yield processes
    for process in processes:
        process.stop()


@pytest.fixture(scope="module")
def site(gateway):  # noqa: F811
    """daphne serving the site; it trusts X-Forwarded-Prefix (sent only by our nginx)."""
    port = stack.free_port()
    process = stack.Process(
        "daphne",
        [sys.executable, "-m", "lifecycle_site.serve", "-b", "127.0.0.1", "-p", str(port),
         "lifecycle_site.asgi:application"],
        stack.environment(LIFECYCLE_TRUST_FORWARDED_PREFIX="1"),
        stack.log_dir(),
    )
    base = f"http://127.0.0.1:{port}/"
    stack.wait_for(lambda: stack.listens(port) or not process.alive(), 30, "daphne to listen")
    assert process.alive(), process.output()
    yield base
    process.stop()



@pytest.fixture(scope="module")
def proxied_site(site):
    """A real nginx that strips /lifecycle/ and passes WebSocket upgrades, like the device's."""
    port, upstream = stack.free_port(), site.rstrip("/")
    server = textwrap.dedent(f"""
        server {{
            listen 127.0.0.1:{port};
            location = /lifecycle {{ return 301 /lifecycle/; }}
            location ~* ^/lifecycle/ {{
                rewrite ^/lifecycle/(.*)$ /$1 break;
                proxy_pass {upstream};
                proxy_http_version 1.1;
                proxy_set_header Upgrade $http_upgrade;
                proxy_set_header Connection $connection_upgrade;
                proxy_set_header Host $host:$server_port;
                proxy_set_header X-Forwarded-Prefix /lifecycle;
                proxy_read_timeout 120s;
            }}
        }}
    """)
    with stack.nginx(Path(settings.DATA_DIR) / "nginx", port, server):
        yield f"http://127.0.0.1:{port}/lifecycle/"


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    assert Path(CHROMIUM).exists(), "Debian's chromium is not installed: make test (or .ci/system-packages) installs it"
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    with sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield chromium
        chromium.close()


@pytest.fixture(scope="module")
def operator(live_db):
    return make_user("bruno-operator", "operator")
