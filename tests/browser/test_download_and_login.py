"""A log download says which filters made it, in its file name and its first lines, whether the
server filtered it or the browser did (regular expressions); after a wrong password the
keyboard is in the password field (issue 26, item 12)."""
from __future__ import annotations

from pathlib import Path

import pytest
from playwright.sync_api import Page, expect

from tests.browser.conftest import ARTIFACTS, ROBOT, logged_in_page, submit_login, watched_page
from tests.integration.conftest import transition

WAIT_MS = 30_000
KEY = f"{ROBOT}.flaky_node"


@pytest.fixture(scope="module")
def refused(robot, operator, api):
    """flaky_node's configure fails (fail_configure) and it says why on /rosout, at ERROR."""
    transition(api, KEY, "configure")


def download(page: Page) -> tuple[str, list[str]]:
    with page.expect_download() as started:
        page.locator("[data-log=download]").click()
    saved = started.value
    path = Path(saved.path())
    return saved.suggested_filename, path.read_text().splitlines()


@pytest.mark.parametrize("regex", [False, True], ids=["server", "browser"])
def test_a_download_names_its_filters(browser, site, refused, regex):
    with logged_in_page(browser, site, accept_downloads=True) as page:
        page.goto(f"{site}logs/node/{KEY}/?level=WARN&q=hardware" + ("&re=1" if regex else ""))
        expect(page.locator(".log-line").filter(has_text="simulated hardware").first).to_be_visible(timeout=WAIT_MS)
        name, lines = download(page)
        (ARTIFACTS / f"download-{'browser' if regex else 'server'}-{name}").write_text("\n".join(lines))
        assert name.startswith(f"node-{KEY}-rosout"), name
        assert "WARN" in name and "hardware" in name, name
        header = "\n".join(line for line in lines[:3] if line.startswith("#"))
        assert "level WARN and above" in header, header
        assert 'text "hardware"' in header, header
        if regex:
            assert "regular expressions" in header, header
        records = [line for line in lines if not line.startswith("#")]
        assert records and all("hardware" in line for line in records), records
        assert all("[INFO]" not in line for line in records)


def test_a_download_without_filters_says_so(browser, site, refused):
    with logged_in_page(browser, site, accept_downloads=True) as page:
        page.goto(f"{site}logs/robot/{ROBOT}/")
        expect(page.locator(".log-line").first).to_be_visible(timeout=WAIT_MS)
        name, lines = download(page)
        assert name == f"robot-{ROBOT}-rosout.log"
        assert lines[1] == "# filters: none (every record kept)", lines[:2]
        page.fill("[data-log=node]", "flaky")
        page.fill("[data-log=xnode]", "camera")
        name, lines = download(page)
        assert "flaky" in name and "camera" in name, name
        assert 'nodes "flaky"' in lines[1] and 'hiding nodes "camera"' in lines[1], lines[1]


@pytest.mark.parametrize("size", [{"width": 1440, "height": 900}, {"width": 390, "height": 844}],
                         ids=["desktop", "phone"])
def test_after_a_wrong_password_the_keyboard_is_in_the_password_field(browser, site, operator, size):
    with watched_page(browser, viewport=size) as page:
        page.goto(site + "login/")
        expect(page.locator("#id_username")).to_be_focused()  # where one starts
        submit_login(page, "bruno-operator", "not-the-password")
        expect(page.locator(".login .error")).to_contain_text("did not match")
        expect(page.locator("#id_password")).to_be_focused()
        expect(page.locator("#id_username")).to_have_value("bruno-operator")
        page.keyboard.type("a-test-password-123")  # straight on, without a click
        page.keyboard.press("Enter")
        expect(page.locator(f"h2:has-text('{ROBOT}')")).to_be_visible(timeout=WAIT_MS)
