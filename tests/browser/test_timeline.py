"""The state timeline on a phone: a node's and its robot's timeline, after a real transition on
the real stack, fit a 390 px wide screen (nothing overflows sideways), name the states and
break no rule of the Content-Security-Policy."""
from __future__ import annotations

from playwright.sync_api import expect

from tests.browser.conftest import ARTIFACTS, ROBOT, submit_login

PHONE = {"width": 390, "height": 844}
WAIT_MS = 20_000
# Tells the test of every Content-Security-Policy violation (as in test_csp.py).
REPORT_VIOLATIONS = """document.addEventListener("securitypolicyviolation", function (e) {
  window.cspViolation(e.violatedDirective + " blocked " + (e.blockedURI || "?"));
});"""


def overflow(page) -> list[str]:
    """What sticks out past the right edge of the viewport (empty when nothing does)."""
    return page.evaluate("""() => {
        const width = document.documentElement.clientWidth;
        const out = [];
        if (document.documentElement.scrollWidth > width) out.push("page " + document.documentElement.scrollWidth);
        for (const el of document.querySelectorAll("main *")) {
            const box = el.getBoundingClientRect();
            const inScroller = el.closest(".table-wrap");  // tables scroll inside their frame by design
            if (box.width && box.right > width + 0.5 && !inScroller) out.push(el.tagName + " " + box.right);
        }
        return out;
    }""")


def test_node_and_robot_timelines_fit_a_phone(browser, site, robot, operator, api):
    key = f"{ROBOT}.lidar_driver"
    answer = api.post(f"/api/v1/nodes/{key}/transition", {"transition": "configure"}, content_type="application/json")
    assert answer.status_code == 200, answer.content
    context = browser.new_context(viewport=PHONE, device_scale_factor=2, is_mobile=True, has_touch=True)
    violations: list[str] = []
    context.expose_binding("cspViolation", lambda _source, text: violations.append(text))
    context.add_init_script(REPORT_VIOLATIONS)
    page = context.new_page()
    try:
        page.goto(site + "login/")
        submit_login(page, "bruno-operator")
        expect(page.locator("h2", has_text=ROBOT)).to_be_visible(timeout=WAIT_MS)
        page.locator(f"#robot-{ROBOT}").get_by_role("link", name="Timeline").click()  # its section on the fleet page
        expect(page.locator("h1")).to_contain_text(f"State timeline {ROBOT}")
        page.get_by_role("link", name="/lidar_driver").click()
        expect(page).to_have_url(site + f"nodes/{key}/timeline/?window=day")
        page.get_by_role("link", name="hour").click()
        expect(page.locator(".tl-windows [aria-current=page]")).to_have_text("hour")
        drawing = page.locator("figure.timeline svg")
        expect(drawing).to_be_visible()
        # Found minutes ago, then configured just now: the table names each stretch.
        legend = page.locator(".tl-legend")
        for state in ("not seen yet", "unconfigured", "inactive"):
            expect(legend).to_contain_text(state)
        box = drawing.bounding_box()
        assert box is not None and box["x"] >= 0 and box["x"] + box["width"] <= PHONE["width"], box
        assert overflow(page) == []
        page.screenshot(path=ARTIFACTS / "timeline-node-phone.png", full_page=True)
        page.goto(site + f"robots/{ROBOT}/timeline/?window=week")
        expect(page.locator(".tl-name", has_text="/lidar_driver")).to_be_visible()
        assert overflow(page) == []
        page.screenshot(path=ARTIFACTS / "timeline-robot-phone.png", full_page=True)
        assert violations == []  # no inline style or script: the drawing works under the policy
    finally:
        context.close()
