"""Alerts that say what is true (issue 26, item 9), in Chromium on the real stack: "About" links to
what the alert is about; an alert resolved while the page is open stays in the default view,
saying so; a stored message holds no "N s ago" that stops moving; a node not in its desired state
that then crashes is still not in its desired state (its alert keeps firing)."""
from __future__ import annotations

import re
import signal
from datetime import timedelta

from django.utils import timezone
from playwright.sync_api import expect

from lifecycle_site.alerts.models import Alert, Rule
from lifecycle_site.fleet.models import Gateway, ManagedNode, Robot
from tests import stack
from tests.browser.conftest import ARTIFACTS, ROBOT, submit_login
from tests.integration.conftest import wait_node

WAIT_MS = 30_000
KEY = f"{ROBOT}.planner"
SILENT = "br-cell-silent"  # a gateway last heard of a minute ago


def test_alert_rows_link_keep_their_word_and_a_crash_does_not_resolve_not_desired(browser, site, robot, operator):
    process = stack.start_robot("br-alert-planner", stack.domain(7), "planner")
    silent = Gateway.objects.create(name=SILENT, last_beat=timezone.now() - timedelta(seconds=60))
    Robot.objects.create(name="br-silent", domain_id=stack.domain(10), gateway=silent)
    rules = [
        Rule.objects.create(name="br-not-desired", kind=Rule.Kind.NOT_DESIRED,
                            robot=Robot.objects.get(name=ROBOT), node_pattern="/planner"),
        Rule.objects.create(name="br-gateway-down", kind=Rule.Kind.GATEWAY_OFFLINE, gateway=silent),
    ]
    page = browser.new_page(viewport={"width": 1440, "height": 900})
    try:
        wait_node(None, KEY, alive=True, state="unconfigured", timeout=30)
        ManagedNode.objects.filter(key=KEY).update(desired_state="active")
        node_alert = stack.wait_for(lambda: Alert.objects.filter(rule=rules[0]).first(), 15, "the node's alert")
        gateway_alert = stack.wait_for(lambda: Alert.objects.filter(rule=rules[1]).first(), 15, "the gateway's alert")
        assert "ago" not in gateway_alert.summary, gateway_alert.summary  # stored: it would never move on

        page.goto(site + "alerts/")
        submit_login(page, "bruno-operator")
        node_row, gateway_row = page.locator(f"#alert-{node_alert.id}"), page.locator(f"#alert-{gateway_alert.id}")
        expect(node_row).to_contain_text("desired state is active",
                                         timeout=WAIT_MS)
        expect(node_row.get_by_role("link", name=re.compile("planner"))).to_have_attribute(
            "href", re.compile(rf"/nodes/{re.escape(KEY)}/$"))
        expect(gateway_row.get_by_role("link", name=re.compile(SILENT))).to_have_attribute(
            "href", re.compile(rf"#gateway-{SILENT}$"))
        expect(gateway_row).to_contain_text(re.compile(r"since \d\d:\d\d:\d\d UTC"))
        expect(gateway_row).not_to_contain_text(" ago")

        # The node crashes: it is still not in its desired state, the alert keeps firing.
        process.stop(signal.SIGKILL)
        wait_node(None, KEY, alive=False)
        page.wait_for_timeout(5_000)  # several evaluations (every second) and a poll of the page (5 s)
        node_alert.refresh_from_db()
        assert node_alert.status == "firing", (node_alert.status, node_alert.resolved_at)
        expect(node_row.locator(".alert-status")).to_have_text("firing")
        page.screenshot(path=ARTIFACTS / "alerts-words.png", full_page=True)

        # Resolved while the page is open: it stays in the default view, saying it resolved.
        ManagedNode.objects.filter(key=KEY).update(desired_state="")
        stack.wait_for(lambda: Alert.objects.get(pk=node_alert.pk).status == "resolved", 15, "the alert to resolve")
        page.wait_for_timeout(6_000)  # the list's next poll
        expect(node_row).to_be_visible()
        expect(node_row.locator(".alert-status")).to_have_text("resolved")
        expect(node_row).to_contain_text(re.compile(r"\d\d:\d\d:\d\d"))
        page.screenshot(path=ARTIFACTS / "alerts-resolved-kept.png", full_page=True)
    finally:
        page.close()
        process.stop()
        for rule in rules:
            rule.delete()
        Alert.objects.filter(rule_name__in=["br-not-desired", "br-gateway-down"]).delete()
        ManagedNode.objects.filter(key=KEY).update(desired_state="")
        Robot.objects.filter(name="br-silent").delete()
        silent.delete()
