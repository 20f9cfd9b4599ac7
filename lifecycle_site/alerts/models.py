"""Alert rules, the alerts they raise (firing, acknowledged, resolved), where alerts are sent
(webhooks, e-mail) and a bounded log of each delivery attempt. How rules are evaluated:
engine.py; how alerts are sent: delivery.py; the design: docs/alerts.md."""
from __future__ import annotations

import fnmatch
import re

from django.conf import settings
from django.core.exceptions import ValidationError
from django.core.validators import MinValueValidator, URLValidator
from django.db import models
from django.db.models import Q
from django.utils.translation import gettext as _
from django.utils.translation import gettext_lazy, pgettext_lazy

from lifecycle_site.alerts import destinations
from ros_gateway.shared import state_machine as sm

NODE_KINDS = ("state", "gone", "not_desired", "not_kept")
# Line breaks and other control characters: in an e-mail header they end it (Django refuses to
# send such a mail at all); in a log line they forge the next one.
CONTROL_CHARACTERS = re.compile(r"[\x00-\x1f\x7f-\x9f\u2028\u2029]+")


def refuse_control_characters(field: str, value: str) -> None:
    if CONTROL_CHARACTERS.search(value):
        raise ValidationError({field: _("Line breaks, tabs and other control characters are not allowed here "
                                        "(the name goes into e-mail subjects and logs).")})


def validate_emails(value: str) -> None:
    from django.core.validators import validate_email

    for address in split_emails(value):
        validate_email(address)


def split_emails(value: str) -> list[str]:
    return [a.strip() for a in value.replace(";", ",").replace("\n", ",").split(",") if a.strip()]


WEBHOOK_URL = URLValidator(schemes=["http", "https"])


def _valid_url(url: str) -> bool:
    """The field's own check passed (its message is enough otherwise)."""
    try:
        WEBHOOK_URL(url)
    except ValidationError:
        return False
    return True


class Receiver(models.Model):
    """Where alerts go: a webhook (JSON POST, signed) or e-mail addresses (Django's mail)."""

    class Kind(models.TextChoices):
        WEBHOOK = "webhook", gettext_lazy("webhook")
        EMAIL = "email", gettext_lazy("e-mail")

    name = models.CharField(gettext_lazy("name"), max_length=80, unique=True)
    kind = models.CharField(gettext_lazy("kind"), max_length=8, choices=Kind.choices, default=Kind.WEBHOOK)
    url = models.CharField(
        gettext_lazy("webhook URL"), max_length=500, blank=True, validators=[URLValidator(schemes=["http", "https"])],
        help_text=gettext_lazy("http:// or https:// address that takes a JSON POST (redirects are not followed)."),
    )
    # Kept in the database (as a Django SECRET_KEY would be in the environment); shown nowhere, never logged.
    secret = models.CharField(
        gettext_lazy("secret"), max_length=200, blank=True,
        help_text=gettext_lazy("Key of the HMAC-SHA256 signature sent in X-Lifecycle-Signature; empty: unsigned."),
    )
    emails = models.TextField(
        gettext_lazy("e-mail addresses"), blank=True, validators=[validate_emails],
        help_text=gettext_lazy("Comma-separated."),
    )
    enabled = models.BooleanField(gettext_lazy("enabled"), default=True)
    # Counted by the ingest process (monotonic: the delivery log is pruned, these are not).
    delivered = models.PositiveBigIntegerField(gettext_lazy("delivered"), default=0, editable=False)
    failed = models.PositiveBigIntegerField(gettext_lazy("failed"), default=0, editable=False,
                                            help_text=gettext_lazy("Gave up after every retry."))
    dropped = models.PositiveBigIntegerField(gettext_lazy("dropped"), default=0, editable=False,
                                             help_text=gettext_lazy("Not sent: the queue was full."))

    class Meta:
        ordering = ["name"]
        verbose_name = gettext_lazy("receiver")
        verbose_name_plural = gettext_lazy("receivers")

    def __str__(self) -> str:
        return f"{self.name} ({self.get_kind_display()})"

    def clean(self) -> None:
        refuse_control_characters("name", self.name)
        if self.kind == self.Kind.WEBHOOK and not self.url:
            raise ValidationError({"url": _("A webhook needs its URL.")})
        if self.kind == self.Kind.WEBHOOK and _valid_url(self.url) and (why := destinations.problem(self.url)):
            raise ValidationError({"url": f"{destinations.redact(self.url)}: {why}."})
        if self.kind == self.Kind.EMAIL and not split_emails(self.emails):
            raise ValidationError({"emails": _("Give at least one e-mail address.")})


class Rule(models.Model):
    """When an alert fires, for which nodes or gateways, and where it is sent."""

    class Kind(models.TextChoices):
        STATE = "state", gettext_lazy("node is in a state")
        GONE = "gone", gettext_lazy("node vanished from the ROS graph")
        NOT_DESIRED = "not_desired", gettext_lazy("node is not in its desired state")
        GATEWAY_OFFLINE = "gateway_offline", gettext_lazy("gateway is offline or quarantined")
        PROCESS_GIVEN_UP = "process_given_up", gettext_lazy("a launch profile's process was given up (kept failing)")
        NOT_KEPT = "not_kept", gettext_lazy(
            "node kept in its desired state was moved, or another manager keeps moving it")
        MODE_NOT_READY = "mode_not_ready", gettext_lazy("robot is not ready in its current mode")
        DIAGNOSTIC = "diagnostic", gettext_lazy("a diagnostic status is at or above a level, or stale")

    class Level(models.TextChoices):
        WARN = "warn", gettext_lazy("WARN or worse")
        ERROR = "error", "ERROR"  # (the diagnostic level's name: the same in every language)
        STALE = "stale", gettext_lazy("stale (not heard)")

    STATE_CHOICES = [(label, label) for state_id, label in sorted(sm.STATE_LABELS.items()) if state_id]

    name = models.CharField(gettext_lazy("name"), max_length=80, unique=True)
    kind = models.CharField(gettext_lazy("kind"), max_length=16, choices=Kind.choices)
    state = models.CharField(
        gettext_lazy("state"), max_length=16, blank=True, choices=STATE_CHOICES,
        help_text=gettext_lazy("For 'node is in a state': e.g. errorprocessing (fires on entering it, however "
                               "briefly) or finalized."),
    )
    for_seconds = models.FloatField(
        gettext_lazy("for (seconds)"), default=0.0, validators=[MinValueValidator(0.0)],
        help_text=gettext_lazy("Fire once the condition has held this long; 0: at once. For 'not in its desired "
                               "state' allow for a bring-up (e.g. 30): a node is not there while it is being "
                               "configured and activated."),
    )
    keep_firing_seconds = models.FloatField(
        gettext_lazy("keep firing for (seconds)"), default=0.0, validators=[MinValueValidator(0.0)],
        help_text=gettext_lazy("Resolve only once the condition has been over this long (a brief state such as "
                               "errorprocessing is over within milliseconds)."),
    )
    # Scope: all of these that are set must match; none set: the whole fleet.
    gateway = models.ForeignKey("fleet.Gateway", verbose_name=gettext_lazy("gateway"), null=True, blank=True,
                                on_delete=models.CASCADE, related_name="+",
                                help_text=gettext_lazy("Only this gateway (or its robots' nodes)."))
    robot = models.ForeignKey("fleet.Robot", verbose_name=gettext_lazy("robot"), null=True, blank=True,
                              on_delete=models.CASCADE, related_name="+",
                              help_text=gettext_lazy("Only this robot's nodes (or its gateway)."))
    node_pattern = models.CharField(
        gettext_lazy("node pattern"), max_length=255, blank=True,
        help_text=gettext_lazy("Only nodes whose fully qualified name matches this pattern (* and ?, e.g. "
                               "/agv1/*_driver)."),
    )
    status_pattern = models.CharField(
        gettext_lazy("status pattern"), max_length=256, blank=True,
        help_text=gettext_lazy("For diagnostic rules: a status name (with what is below it, e.g. /Robot/Sensors), or "
                               "a pattern with * and ? (e.g. lidar_driver: *); empty: every status."),
    )
    level = models.CharField(gettext_lazy("level"), max_length=8, blank=True, choices=Level.choices,
                             help_text=gettext_lazy("For diagnostic rules: the level that fires it."))
    receivers = models.ManyToManyField(Receiver, verbose_name=gettext_lazy("receivers"), blank=True,
                                       related_name="rules")
    enabled = models.BooleanField(gettext_lazy("enabled"), default=True)
    created = models.DateTimeField(gettext_lazy("created"), auto_now_add=True)

    class Meta:
        ordering = ["name"]
        verbose_name = gettext_lazy("rule")
        verbose_name_plural = gettext_lazy("rules")

    def __str__(self) -> str:
        return self.name

    def clean(self) -> None:
        refuse_control_characters("name", self.name)
        if self.kind == self.Kind.STATE and not self.state:
            raise ValidationError({"state": _("Choose the state this rule watches for.")})
        if self.kind != self.Kind.STATE and self.state:
            raise ValidationError({"state": _("Only 'node is in a state' rules take a state.")})
        if self.kind == self.Kind.GATEWAY_OFFLINE and self.node_pattern:
            raise ValidationError({"node_pattern": _("A gateway rule has no node pattern.")})
        if self.kind == self.Kind.MODE_NOT_READY and self.node_pattern:
            raise ValidationError({"node_pattern": _("A mode rule has no node pattern (it watches robots).")})
        if self.kind == self.Kind.DIAGNOSTIC and not self.level:
            raise ValidationError({"level": _("Choose the level this rule fires at (WARN or worse, ERROR, stale).")})
        if self.kind == self.Kind.DIAGNOSTIC and self.node_pattern:
            raise ValidationError({"node_pattern": _("A diagnostic rule names statuses (status pattern), not nodes.")})
        if self.kind != self.Kind.DIAGNOSTIC and (self.level or self.status_pattern):
            raise ValidationError({"level": _("Only diagnostic rules take a level and a status pattern.")})
        if self.kind == self.Kind.PROCESS_GIVEN_UP and self.node_pattern:
            raise ValidationError({"node_pattern": _("A process rule has no node pattern (it watches every launch "
                                                     "profile of its robot or gateway).")})

    @property
    def watches_nodes(self) -> bool:
        return self.kind in NODE_KINDS

    def matches_node(self, name: str) -> bool:
        return not self.node_pattern or fnmatch.fnmatchcase(name, self.node_pattern)

    def matches_status(self, name: str) -> bool:
        """The status itself, what is below it in the tree, or a * and ? pattern."""
        pattern = self.status_pattern
        if not pattern or name == pattern:
            return True
        if "*" in pattern or "?" in pattern:
            return fnmatch.fnmatchcase(name, pattern)
        return name.startswith(pattern.rstrip("/") + "/")

    def describe(self) -> str:
        """'node is in a state errorprocessing, for 5 s'"""
        text = self.get_kind_display() + (f" {self.state}" if self.state else "")
        if self.kind == self.Kind.DIAGNOSTIC:
            text = _("diagnostic status %(pattern)s %(level)s") % {
                "pattern": self.status_pattern or _("(any)"), "level": self.get_level_display()}
        if not self.for_seconds:
            return text
        return _("%(rule)s, for %(seconds)s s") % {"rule": text, "seconds": f"{self.for_seconds:g}"}

    def as_dict(self) -> dict:
        return {
            "id": self.id,
            "name": self.name,
            "kind": self.kind,
            "state": self.state or None,
            "for_seconds": self.for_seconds,
            "keep_firing_seconds": self.keep_firing_seconds,
            "gateway": self.gateway.name if self.gateway_id else None,
            "robot": self.robot.name if self.robot_id else None,
            "node_pattern": self.node_pattern,
            "status_pattern": self.status_pattern,
            "level": self.level or None,
            "receivers": sorted(r.name for r in self.receivers.all()),
            "enabled": self.enabled,
        }


class Alert(models.Model):
    """One firing of a rule for one node or gateway, from firing to resolved."""

    class Status(models.TextChoices):
        FIRING = "firing", pgettext_lazy("alert status", "firing")
        ACKNOWLEDGED = "acknowledged", pgettext_lazy("alert status", "acknowledged")
        RESOLVED = "resolved", pgettext_lazy("alert status", "resolved")

    ACTIVE = (Status.FIRING, Status.ACKNOWLEDGED)

    # Kept (by name) when its rule is deleted; an active one is then resolved.
    rule = models.ForeignKey(Rule, verbose_name=gettext_lazy("rule"), null=True, blank=True, on_delete=models.SET_NULL,
                             related_name="alerts")
    rule_name = models.CharField(gettext_lazy("rule name"), max_length=80)
    # A node's key (robot.node) or a gateway's name: what the alert is about.
    subject = models.CharField(pgettext_lazy("alert", "subject"), max_length=320)
    gateway_name = models.CharField(gettext_lazy("gateway name"), max_length=63, blank=True)
    robot_name = models.CharField(gettext_lazy("robot name"), max_length=63, blank=True)
    node_name = models.CharField(gettext_lazy("node name"), max_length=255, blank=True)
    status = models.CharField(gettext_lazy("status"), max_length=16, choices=Status.choices, default=Status.FIRING)
    summary = models.TextField(gettext_lazy("summary"))
    since = models.DateTimeField(gettext_lazy("since"), help_text=gettext_lazy("When the condition began."))
    fired_at = models.DateTimeField(gettext_lazy("fired at"))
    resolved_at = models.DateTimeField(gettext_lazy("resolved at"), null=True, blank=True)
    acknowledged_at = models.DateTimeField(gettext_lazy("acknowledged at"), null=True, blank=True)
    acknowledged_by = models.ForeignKey(settings.AUTH_USER_MODEL, verbose_name=gettext_lazy("acknowledged by"),
                                        null=True, blank=True, on_delete=models.SET_NULL, related_name="+")
    acknowledged_by_name = models.CharField(gettext_lazy("acknowledged by name"), max_length=150, blank=True)

    class Meta:
        ordering = ["-fired_at", "-id"]
        permissions = [("acknowledge_alert", "Can acknowledge alerts")]
        constraints = [
            # At most one unresolved alert per rule and subject.
            models.UniqueConstraint(fields=["rule", "subject"], condition=~Q(status="resolved"),
                                    name="one_active_alert_per_rule_subject"),
        ]
        indexes = [models.Index(fields=["status", "-fired_at"], name="alert_status_recent")]
        verbose_name = gettext_lazy("alert")
        verbose_name_plural = gettext_lazy("alerts")

    def __str__(self) -> str:
        return f"{self.rule_name}: {self.subject} ({self.status})"

    @property
    def active(self) -> bool:
        return self.status in self.ACTIVE

    def as_dict(self) -> dict:
        def moment(value):
            return value.isoformat() if value else None

        return {
            "id": self.id,
            "rule": self.rule_name,
            "kind": self.rule.kind if self.rule_id else None,
            "status": self.status,
            "subject": self.subject,
            "gateway": self.gateway_name or None,
            "robot": self.robot_name or None,
            "node": self.node_name or None,
            "summary": self.summary,
            "since": moment(self.since),
            "fired_at": moment(self.fired_at),
            "resolved_at": moment(self.resolved_at),
            "acknowledged_at": moment(self.acknowledged_at),
            "acknowledged_by": self.acknowledged_by_name or None,
        }


class Delivery(models.Model):
    """One attempt to send one alert event to one receiver (pruned to ALERTS['DELIVERY_LOG_KEEP'])."""

    class Outcome(models.TextChoices):
        DELIVERED = "delivered", gettext_lazy("delivered")
        RETRYING = "retrying", gettext_lazy("failed, will retry")
        FAILED = "failed", gettext_lazy("failed, gave up")
        DROPPED = "dropped", gettext_lazy("dropped (queue full)")

    alert = models.ForeignKey(Alert, verbose_name=gettext_lazy("alert"), null=True, on_delete=models.SET_NULL,
                              related_name="deliveries")
    receiver = models.ForeignKey(Receiver, verbose_name=gettext_lazy("receiver"), null=True, on_delete=models.SET_NULL,
                                 related_name="deliveries")
    receiver_name = models.CharField(gettext_lazy("receiver name"), max_length=80)
    event = models.CharField(gettext_lazy("event"), max_length=16)  # firing | resolved
    attempt = models.PositiveSmallIntegerField(gettext_lazy("attempt"), default=1)
    outcome = models.CharField(gettext_lazy("outcome"), max_length=16, choices=Outcome.choices)
    status_code = models.PositiveSmallIntegerField(gettext_lazy("status code"), null=True, blank=True)
    error = models.TextField(gettext_lazy("error"), blank=True)
    duration_ms = models.FloatField(gettext_lazy("duration ms"), null=True, blank=True)
    at = models.DateTimeField(gettext_lazy("at"))

    class Meta:
        ordering = ["-at", "-id"]
        verbose_name_plural = gettext_lazy("deliveries")
        verbose_name = gettext_lazy("delivery")

    def __str__(self) -> str:
        return f"{self.event} to {self.receiver_name}: {self.outcome}"
