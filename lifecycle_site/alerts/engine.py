"""The alert evaluator: runs inside the ingest process (``manage.py ingest``), which holds the
one lease to write what gateways report, so alerts are evaluated once per site.

Each turn of the ingest loop calls ``tick()``: it writes the delivery attempts the workers
finished, and (every EVALUATE_S, or at once when facts arrived) compares each enabled rule's
conditions with the active alerts: a condition that has held ``for_seconds`` fires an alert;
an alert whose condition has been over ``keep_firing_seconds`` is resolved. Both are sent to
the rule's receivers. ``observe()`` hands over the facts just stored, so that a state a node
passes through in milliseconds (errorprocessing) fires too. See docs/alerts.md.
"""
from __future__ import annotations

import json
import logging
import time
import uuid
from collections import deque
from datetime import datetime, timedelta

from django.conf import settings
from django.db import IntegrityError, InterfaceError, OperationalError, transaction
from django.db.models import F
from django.utils import timezone, translation
from django.utils.translation import gettext as _

from lifecycle_site.alerts import conditions as cond
from lifecycle_site.alerts.delivery import Dispatcher, Job, Result
from lifecycle_site.alerts.models import CONTROL_CHARACTERS, Alert, Delivery, Receiver, Rule, split_emails
from lifecycle_site.ingest.observations import Observation, observations

log = logging.getLogger(__name__)

EVALUATE_S = 1.0
PRUNE_S = 60.0
OBSERVATIONS_KEPT = 10_000  # between two evaluations (a second's facts)


class Evaluator:
    def __init__(self, dispatcher: Dispatcher | None = None) -> None:
        self.dispatcher = dispatcher or Dispatcher()
        self.observed: deque[Observation] = deque(maxlen=OBSERVATIONS_KEPT)
        # (rule id, subject) -> when its condition was last seen holding (for keep_firing_seconds).
        self.last_true: dict[tuple[int, str], datetime] = {}
        self.due = 0.0
        self.prune_due = time.monotonic() + PRUNE_S
        self.last_complaint = 0.0

    # --- the hooks of the ingest loop ---------------------------------------------------------

    def observe(self, gateway: str, facts: list[dict]) -> None:
        """Facts of one gateway just stored (cheap: evaluated at the next tick)."""
        self.take(observations(gateway, facts))

    def take(self, seen: list[Observation]) -> None:
        self.observed.extend(seen)

    def stop(self) -> None:
        self.dispatcher.stop()

    def tick(self) -> None:
        """One turn; never raises, but for the database being unavailable (ingest retries)."""
        try:
            self.store_results()
            now = time.monotonic()
            if self.observed or now >= self.due:
                self.due = now + EVALUATE_S
                self.evaluate()
            if now >= self.prune_due:
                self.prune_due = now + PRUNE_S
                prune()
        except (OperationalError, InterfaceError):
            raise
        except Exception:  # noqa: BLE001 - alerts must never stop what the ingest process stores
            if time.monotonic() - self.last_complaint > 30:
                self.last_complaint = time.monotonic()
                log.exception("alert evaluation failed; trying again next second")

    # --- evaluation -------------------------------------------------------------------------

    def evaluate(self, now: datetime | None = None) -> None:
        now = now or timezone.now()
        seen = list(self.observed)
        self.observed.clear()
        rules = {r.id: r for r in Rule.objects.filter(enabled=True).select_related("robot", "gateway")}
        active = {(a.rule_id, a.subject): a for a in Alert.objects.filter(status__in=Alert.ACTIVE)}
        holding: set[tuple[int, str]] = set()
        for rule in rules.values():
            # An alert's summary is stored, mailed and shown as stored: in the site's language
            # (LIFECYCLE_LANGUAGE), like the rest of its e-mails and webhooks.
            with translation.override(settings.LANGUAGE_CODE):
                found = cond.current(rule, now)
                from_facts = cond.from_facts(rule, seen)
            for subject in found:
                self.last_true[(rule.id, subject)] = now
            for subject, brief in from_facts.items():
                if subject not in found:  # over already: it held until the moment it was seen
                    found[subject] = brief
                    key = (rule.id, subject)
                    self.last_true[key] = max(brief.since, self.last_true.get(key, brief.since))
            for subject, condition in found.items():
                key = (rule.id, subject)
                holding.add(key)
                if key not in active and (now - condition.since).total_seconds() >= rule.for_seconds:
                    self.fire(rule, condition, now)
        for key, alert in active.items():
            rule = rules.get(alert.rule_id)
            if rule is None:
                self.resolve(alert, None, now, "its rule was disabled or deleted")
            elif key not in holding:
                last = self.last_true.setdefault(key, now)
                if (now - last).total_seconds() >= rule.keep_firing_seconds:
                    self.resolve(alert, rule, now, "")
        self.last_true = {k: v for k, v in self.last_true.items() if k in holding or k in active}

    def fire(self, rule: Rule, condition: cond.Condition, now: datetime) -> Alert | None:
        try:
            with transaction.atomic():
                alert = Alert.objects.create(
                    rule=rule, rule_name=rule.name, subject=condition.subject, gateway_name=condition.gateway,
                    robot_name=condition.robot, node_name=condition.node, summary=condition.summary,
                    since=condition.since, fired_at=now,
                )
        except IntegrityError:  # already active (another evaluator got there first)
            return None
        log.info("alert %s fired: %s: %s", alert.id, rule.name, condition.summary)
        self.notify(alert, rule, "firing")
        return alert

    def resolve(self, alert: Alert, rule: Rule | None, now: datetime, why: str) -> None:
        if not Alert.objects.filter(pk=alert.pk, status__in=Alert.ACTIVE).update(status=Alert.Status.RESOLVED,
                                                                                   resolved_at=now):
            return
        alert.refresh_from_db()  # who acknowledged it meanwhile goes with the notification
        log.info("alert %s resolved: %s: %s%s", alert.id, alert.rule_name, alert.subject, f" ({why})" if why else "")
        if rule is not None:
            self.notify(alert, rule, "resolved")

    # --- delivery ---------------------------------------------------------------------------

    def notify(self, alert: Alert, rule: Rule, event: str) -> None:
        alert.rule = rule
        for receiver in rule.receivers.filter(enabled=True):
            job = make_job(receiver, alert, event)
            if not self.dispatcher.submit(job):
                log.warning("alert %s (%s) to %s dropped: %d deliveries are queued already",
                            alert.id, event, receiver.name, settings.ALERTS["QUEUE_SIZE"])
                Receiver.objects.filter(pk=receiver.pk).update(dropped=F("dropped") + 1)
                Delivery.objects.create(alert=alert, receiver=receiver, receiver_name=receiver.name, event=event,
                                        attempt=0, outcome=Delivery.Outcome.DROPPED, at=timezone.now(),
                                        error="not sent: the delivery queue was full")

    def store_results(self) -> None:
        """The attempts the workers made since the last turn, into the delivery log."""
        results: list[Result] = []
        while self.dispatcher.results:
            results.append(self.dispatcher.results.popleft())
        if not results:
            return
        known = set(Alert.objects.filter(pk__in={r.job.alert_id for r in results}).values_list("pk", flat=True))
        receivers = set(Receiver.objects.filter(pk__in={r.job.receiver_id for r in results})
                        .values_list("pk", flat=True))
        rows = []
        for result in results:
            job = result.job
            rows.append(Delivery(
                alert_id=job.alert_id if job.alert_id in known else None,
                receiver_id=job.receiver_id if job.receiver_id in receivers else None,
                receiver_name=job.receiver_name, event=job.event, attempt=result.attempt, outcome=result.outcome,
                status_code=result.status_code, error=result.error, duration_ms=result.duration_ms, at=result.at,
            ))
            counter = {"delivered": "delivered", "failed": "failed"}.get(result.outcome)
            if counter and job.receiver_id in receivers:
                Receiver.objects.filter(pk=job.receiver_id).update(**{counter: F(counter) + 1})
        Delivery.objects.bulk_create(rows)


def payload(alert: Alert, event: str, delivery_id: str) -> dict:
    """The webhook's body: codes and what the alert stored (its summary is English, as stored); any
    human text added here is in the site's language (LIFECYCLE_LANGUAGE: a webhook has no browser)."""
    site = settings.ALERTS["SITE_URL"]
    with translation.override(settings.LANGUAGE_CODE):
        return {
            "version": 1,
            "event": event,
            "delivery": delivery_id,
            "sent_at": timezone.now().isoformat(),
            "alert": {**alert.as_dict(), "url": f"{site}/alerts/#alert-{alert.id}" if site else None},
        }


def email_text(alert: Alert, event: str) -> tuple[str, str]:
    """The e-mail's subject and body, in the site's language (LIFECYCLE_LANGUAGE: a mail has no browser)."""
    with translation.override(settings.LANGUAGE_CODE):
        values = {"rule": alert.rule_name, "subject": alert.subject}
        if event == "resolved":
            heading = _("[RESOLVED] %(rule)s: %(subject)s") % values
        else:
            heading = _("[FIRING] %(rule)s: %(subject)s") % values
        # No line breaks in a header, whatever was stored (Django refuses to send the mail otherwise)
        subject = CONTROL_CHARACTERS.sub(" ", heading)
        lines = [alert.summary, "", _("Rule: %(rule)s") % {"rule": alert.rule_name},
                 _("Since: %(time)s") % {"time": alert.since.isoformat()},
                 _("Fired: %(time)s") % {"time": alert.fired_at.isoformat()}]
        if alert.resolved_at:
            lines.append(_("Resolved: %(time)s") % {"time": alert.resolved_at.isoformat()})
    if settings.ALERTS["SITE_URL"]:
        lines += ["", f"{settings.ALERTS['SITE_URL']}/alerts/#alert-{alert.id}"]
    return subject, "\n".join(lines) + "\n"


def make_job(receiver: Receiver, alert: Alert, event: str) -> Job:
    delivery_id = uuid.uuid4().hex
    job = Job(receiver.id, receiver.name, receiver.kind, alert.id, event, delivery_id)
    if receiver.kind == Receiver.Kind.WEBHOOK:
        job.url, job.secret = receiver.url, receiver.secret
        job.body = json.dumps(payload(alert, event, delivery_id), separators=(",", ":")).encode()
    else:
        job.emails = split_emails(receiver.emails)
        job.subject, job.text = email_text(alert, event)
    return job


def prune() -> None:
    """Keep the delivery log to its last DELIVERY_LOG_KEEP attempts and resolved alerts for
    RESOLVED_KEEP_DAYS."""
    cfg = settings.ALERTS
    edge = Delivery.objects.order_by("-id").values_list("id", flat=True)[cfg["DELIVERY_LOG_KEEP"]:][:1]
    if edge:
        Delivery.objects.filter(id__lte=edge[0]).delete()
    cutoff = timezone.now() - timedelta(days=cfg["RESOLVED_KEEP_DAYS"])
    Alert.objects.filter(status=Alert.Status.RESOLVED, resolved_at__lt=cutoff).delete()
