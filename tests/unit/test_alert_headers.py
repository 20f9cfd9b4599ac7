"""Names that go into e-mail headers: refused with line breaks (and other control characters)
when saved through the API or the admin; a stored one still gives a mail that is sent."""
from __future__ import annotations

import pytest
from django.core import mail
from django.utils import timezone

from lifecycle_site.alerts import installed_rules
from lifecycle_site.alerts.engine import Evaluator
from lifecycle_site.alerts.models import Delivery, Receiver, Rule
from lifecycle_site.fleet.models import Gateway, ManagedNode, Robot
from tests import stack
from tests.unit.test_alerts_api import client_of
from tests.unit.test_alerts_delivery import drain

INSTALLED_RULES = [name for name, _, _ in installed_rules.INSTALLED_RULES]  # made after every migrate

REFUSED = "Line breaks, tabs and other control characters are not allowed here"


# (at either end, the forms strip them as whitespace: what is saved has none)
@pytest.mark.parametrize("name", ["finalized\r\nBcc: everyone@example.invalid", "final\nized", "tab\there",
                                  "bell\x07", "next\x85line", "line\u2028separator"])
def test_rule_and_receiver_names_with_control_characters_are_refused(db, name):
    admin = client_of("ada-admin", "admin")
    answer = admin.post("/api/v1/alert-rules", {"name": name, "kind": "state", "state": "finalized"},
                        content_type="application/json")
    assert answer.status_code == 400, answer.json()
    error = answer.json()["error"]
    assert error["code"] == "invalid_rule" and error["fields"]["name"][0].startswith(REFUSED)
    page = admin.post("/admin/alerts/rule/add/", {"name": name, "enabled": "on", "kind": "state",
                                                  "state": "finalized", "for_seconds": "0",
                                                  "keep_firing_seconds": "0"})
    assert REFUSED in page.content.decode()
    page = admin.post("/admin/alerts/receiver/add/", {"name": name, "kind": "email", "url": "", "secret": "",
                                                      "emails": "shift@example.invalid", "enabled": "on"})
    assert REFUSED in page.content.decode()
    made = Rule.objects.exclude(name__in=INSTALLED_RULES)  # (the rules made at installation stay)
    assert not made.exists() and not Receiver.objects.exists()
    rule = Rule.objects.create(name="finalized", kind=Rule.Kind.STATE, state="finalized")
    renamed = admin.patch(f"/api/v1/alert-rules/{rule.pk}", {"name": name}, content_type="application/json")
    assert renamed.status_code == 400 and made.get().name == "finalized"


def test_a_stored_name_with_a_line_break_still_gives_an_email_that_is_sent(db, settings):
    """A rule saved before names were checked: its alerts' e-mails were all refused by Django
    ("Header values can't contain newlines") and retried in vain."""
    settings.ALERTS = {**settings.ALERTS, "RETRY_BASE_S": 0.2, "RETRY_CAP_S": 1.0, "ATTEMPTS": 3}
    robot = Robot.objects.create(name="hd-agv", domain_id=67, gateway=Gateway.objects.create(name="hd-cell"))
    now = timezone.now()
    ManagedNode.objects.create(robot=robot, name="/planner", alive=True, state_label="finalized", state_id=4,
                               first_seen=now, last_seen=now, state_changed=now)
    team = Receiver.objects.create(name="shift-team", kind=Receiver.Kind.EMAIL, emails="shift@example.invalid")
    rule = Rule.objects.create(name="finalized\r\nBcc: everyone@example.invalid", kind=Rule.Kind.STATE,
                               state="finalized")
    rule.receivers.add(team)
    evaluator = Evaluator()
    try:
        evaluator.evaluate()
        drain(evaluator, lambda: Delivery.objects.filter(outcome__in=("delivered", "failed")).exists())
    finally:
        evaluator.dispatcher.stop()
    assert list(Delivery.objects.values_list("outcome", "error")) == [("delivered", "")]
    stack.wait_for(lambda: len(mail.outbox) == 1, 5, "the e-mail")
    message = mail.outbox[0]
    assert message.subject == "[FIRING] finalized Bcc: everyone@example.invalid: hd-agv.planner"
    assert message.recipients() == ["shift@example.invalid"]
    assert "\n" not in message.message()["Subject"]
