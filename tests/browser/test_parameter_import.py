"""Importing a parameter file (issue 26, item 6): the preview checks each value as the gateway
would before sending it (type, the descriptor's range, read-only, unknown names), Apply sets
the valid ones all together or none, and a value the node itself refuses stays on the page with
the node's reason beside it. Real lidar and flaky nodes, at desktop and phone sizes."""
from __future__ import annotations

import re

from playwright.sync_api import Page, expect

from lifecycle_site.audit.models import ParameterRecord
from tests.browser.conftest import ARTIFACTS, ROBOT, logged_in_page

WAIT_MS = 30_000
DESKTOP = {"width": 1440, "height": 900}
PHONE = {"width": 390, "height": 844}


def node_values(api, node: str) -> dict:
    listing = api.get(f"/api/v1/nodes/{ROBOT}.{node}/parameters").json()["parameters"]
    return {p["name"]: p["value"] for p in listing}


def import_file(page: Page, name: str, text: str) -> None:
    page.locator("#parameters input[type=file]").set_input_files(
        {"name": name, "mimeType": "application/x-yaml", "buffer": text.encode()})
    page.get_by_role("button", name="Preview").click()
    expect(page.locator("#parameters .preview")).to_be_visible(timeout=WAIT_MS)


def row(page: Page, name: str):
    return page.locator("#parameters .preview tr", has_text=name)


def apply(page: Page) -> None:
    page.locator("#parameters .preview").get_by_role("button", name=re.compile("^Apply")).click()
    expect(page.locator("#parameters p.result")).to_be_visible(timeout=WAIT_MS)


def fits(page: Page) -> list[str]:
    """What of the preview reaches past the right edge of the screen."""
    return page.evaluate("""() => Array.from(document.querySelectorAll('#parameters .preview, #parameters .preview *'))
        .filter((el) => el.getClientRects().length && el.getBoundingClientRect().right > window.innerWidth + 0.5)
        .map((el) => el.tagName + ' ' + Math.round(el.getBoundingClientRect().right))""")


def test_the_preview_leaves_out_what_the_gateway_would_refuse_and_applies_the_rest(browser, site, robot, operator,
                                                                                    api):
    before = node_values(api, "lidar_driver")
    last_record = ParameterRecord.objects.order_by("-id").values_list("id", flat=True).first() or 0
    text = ("lidar_driver:\n  ros__parameters:\n    scan_rate_hz: 99.0\n    range_max: 20.0\n"
            "    frame_id: base_scan\n    num_points: many\n    no_such: 1\n")
    with logged_in_page(browser, site, viewport=DESKTOP) as page:
        page.goto(f"{site}nodes/{ROBOT}.lidar_driver/")
        import_file(page, "lidar.yaml", text)
        preview = page.locator("#parameters .preview")
        # Each value is checked as the gateway checks it before sending (scan_rate_hz is 1-40).
        expect(row(page, "scan_rate_hz")).to_contain_text("left out: must be between 1 and 40")
        expect(row(page, "num_points")).to_contain_text("left out: must be a whole number")
        expect(row(page, "frame_id")).to_contain_text("left out: is read-only")
        expect(row(page, "no_such")).to_contain_text("left out: the node has no such parameter")
        expect(row(page, "range_max")).to_contain_text("valid")
        expect(preview).to_contain_text("Apply sets the 1 valid value together: the node takes all of them or none.")
        expect(preview.get_by_role("button", name=re.compile("^Apply"))).to_have_text("Apply 1 valid change")
        page.screenshot(path=ARTIFACTS / "parameter-import-preview-desktop.png", full_page=True)
        apply(page)
        expect(page.locator("#parameters")).to_contain_text("All changes accepted by the node.")
        expect(page.locator("#param-value-range_max")).to_have_text("20.0")
        assert page.console_errors == []
    after = node_values(api, "lidar_driver")
    assert after["range_max"] == 20.0 and after["scan_rate_hz"] == before["scan_rate_hz"]
    # The values left out were never sent: no refused attempt is on record for them.
    tried = set(ParameterRecord.objects.filter(node__key=f"{ROBOT}.lidar_driver", id__gt=last_record)
                .values_list("name", flat=True))
    assert tried == {"range_max"}  # (earlier modules' records of this node are left aside)


def test_a_value_the_node_refuses_sets_nothing_and_stays_with_its_reason_on_a_phone(browser, site, robot, operator,
                                                                                     api):
    before = node_values(api, "flaky_node")
    assert before["slow_seconds"] != 9.5
    text = "flaky_node:\n  ros__parameters:\n    slow_seconds: 9.5\n    failure_mode: bogus\n"
    with logged_in_page(browser, site, viewport=PHONE, device_scale_factor=1, is_mobile=True, has_touch=True) as page:
        page.goto(f"{site}nodes/{ROBOT}.flaky_node/")
        import_file(page, "flaky.yaml", text)
        # Both pass the gateway's checks; only the node knows "bogus" is no failure mode.
        apply(page)
        # All or none: the valid value did not go in without the other.
        assert node_values(api, "flaky_node") == before
        preview = page.locator("#parameters .preview")
        expect(preview.get_by_role("alert")).to_contain_text("Nothing was set: the node refused these values")
        # What the file asked for is still shown, the node's own reason beside the value it refused.
        refused = row(page, "failure_mode")
        expect(refused).to_contain_text("bogus")
        expect(refused).to_contain_text("refused by the node: unknown failure_mode 'bogus'")
        expect(row(page, "slow_seconds")).to_contain_text("not set: the node took none of these values")
        expect(page.locator("#param-value-slow_seconds")).to_have_text(str(before["slow_seconds"]))
        assert page.evaluate("document.documentElement.scrollWidth") <= PHONE["width"]
        assert fits(page) == []
        preview.locator("h3").scroll_into_view_if_needed()
        page.screenshot(path=ARTIFACTS / "parameter-import-refused-phone.png")  # the screen the operator sees
        assert page.console_errors == []
