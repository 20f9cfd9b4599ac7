"""The audit log: one append-only record per lifecycle state change or attempt."""
from __future__ import annotations

from django.conf import settings
from django.db import models
from django.utils.translation import gettext_lazy, pgettext_lazy


class AppendOnlyError(Exception):
    """Raised on any attempt to change or delete an audit record."""


class AppendOnlyQuerySet(models.QuerySet):
    def update(self, **kwargs):  # noqa: D102 - guard, see AppendOnlyError
        raise AppendOnlyError("Audit records cannot be changed.")

    def delete(self):  # noqa: D102
        raise AppendOnlyError("Audit records cannot be deleted.")


class AppendOnlyRecord(models.Model):
    """Base of audit records: written once, never changed or deleted (nor through querysets)."""

    requested_by = models.ForeignKey(
        settings.AUTH_USER_MODEL, verbose_name=gettext_lazy("requested by"), null=True, blank=True,
        on_delete=models.SET_NULL, related_name="+"
    )
    requested_by_name = models.CharField(gettext_lazy("requested by name"), max_length=150, blank=True)

    objects = AppendOnlyQuerySet.as_manager()

    class Meta:
        abstract = True

    def save(self, *args, **kwargs) -> None:
        if self.pk is not None:
            raise AppendOnlyError("Audit records cannot be changed.")
        if not self.requested_by_name and self.requested_by is not None:
            self.requested_by_name = self.requested_by.get_username()
        super().save(*args, **kwargs)

    def delete(self, *args, **kwargs):
        raise AppendOnlyError("Audit records cannot be deleted.")


class TransitionRecord(AppendOnlyRecord):
    class Outcome(models.TextChoices):
        SUCCEEDED = "succeeded", pgettext_lazy("outcome", "succeeded")
        FAILED = "failed", pgettext_lazy("outcome", "failed")
        REJECTED = "rejected", pgettext_lazy("outcome", "rejected")
        TIMED_OUT = "timed_out", pgettext_lazy("outcome", "timed out")
        OBSERVED = "observed", pgettext_lazy("outcome", "observed")
        # Not transitions: the node's process ended (during a transition, or by itself), or a
        # new instance of it appeared (its state then read fresh). See ros_gateway/processes.py.
        PROCESS_LOST = "process_lost", gettext_lazy("process lost")
        PROCESS_RESTARTED = "process_restarted", gettext_lazy("process restarted (new instance)")

    class Source(models.TextChoices):
        DASHBOARD = "dashboard", pgettext_lazy("source", "dashboard")
        API = "api", "API"  # (the same word in every language)
        EXTERNAL = "external", gettext_lazy("external tool")
        RECOVERY = "recovery", gettext_lazy("automatic recovery")
        CLI = "cli", pgettext_lazy("source", "command line")

    # Kept as plain text too, so the record stays readable after a node or robot is deleted.
    node = models.ForeignKey(
        "fleet.ManagedNode", verbose_name=gettext_lazy("node"), null=True, blank=True, on_delete=models.SET_NULL,
        related_name="transitions"
    )
    robot = models.ForeignKey(
        "fleet.Robot", verbose_name=gettext_lazy("robot"), null=True, blank=True, on_delete=models.SET_NULL,
        related_name="transitions"
    )
    robot_name = models.CharField(gettext_lazy("robot name"), max_length=63)
    node_name = models.CharField(gettext_lazy("node name"), max_length=255)
    transition_id = models.PositiveSmallIntegerField(gettext_lazy("transition id"), null=True, blank=True)
    transition_label = models.CharField(gettext_lazy("transition label"), max_length=64, blank=True)
    start_state_id = models.PositiveSmallIntegerField(gettext_lazy("start state id"), null=True, blank=True)
    start_state_label = models.CharField(gettext_lazy("start state label"), max_length=32, blank=True)
    goal_state_id = models.PositiveSmallIntegerField(gettext_lazy("goal state id"), null=True, blank=True)
    goal_state_label = models.CharField(gettext_lazy("goal state label"), max_length=32, blank=True)
    result_state_id = models.PositiveSmallIntegerField(gettext_lazy("result state id"), null=True, blank=True)
    result_state_label = models.CharField(gettext_lazy("result state label"), max_length=32, blank=True)
    outcome = models.CharField(gettext_lazy("outcome"), max_length=20, choices=Outcome.choices)
    source = models.CharField(gettext_lazy("source"), max_length=16, choices=Source.choices)
    requested_at = models.DateTimeField(gettext_lazy("requested at"))
    completed_at = models.DateTimeField(gettext_lazy("completed at"), null=True, blank=True)
    duration_ms = models.FloatField(gettext_lazy("duration ms"), null=True, blank=True)
    error = models.TextField(gettext_lazy("error"), blank=True)
    run_id = models.CharField(gettext_lazy("run id"), max_length=64, blank=True,
                              help_text=gettext_lazy("Groups the steps of one group operation."))
    # The id of the gateway's fact this record was made from: applying a fact twice makes one record.
    fact_id = models.CharField(gettext_lazy("fact id"), max_length=32, null=True, blank=True, unique=True,
                               editable=False)

    class Meta:
        ordering = ["-requested_at", "-id"]
        indexes = [
            models.Index(fields=["robot_name", "-requested_at"], name="audit_robot_recent"),
            models.Index(fields=["node", "-requested_at"], name="audit_node_recent"),
            # Covering indexes of the state timeline's counts over a window (timelines/node.py),
            # read without a visit to the table's rows: a node's records by outcome, and a robot's
            # failures and restarts only (a few among a week's records).
            models.Index(fields=["node", "requested_at", "outcome"], name="audit_node_outcomes"),
            models.Index(fields=["robot_name", "outcome", "requested_at", "node"], name="audit_robot_outcomes"),
        ]
        verbose_name = gettext_lazy("transition record")
        verbose_name_plural = gettext_lazy("transition records")

    def __str__(self) -> str:
        return f"{self.robot_name}:{self.node_name} {self.transition_label} {self.outcome}"

    def as_dict(self) -> dict:
        def state(state_id, label):
            return None if state_id is None else {"id": state_id, "label": label}

        return {
            "id": self.id,
            "robot": self.robot_name,
            "node": self.node_name,
            "node_id": self.node.key if self.node_id and self.node else None,
            "transition": {"id": self.transition_id, "label": self.transition_label}
            if self.transition_id is not None or self.transition_label
            else None,
            "from": state(self.start_state_id, self.start_state_label),
            "goal": state(self.goal_state_id, self.goal_state_label),
            "to": state(self.result_state_id, self.result_state_label),
            "outcome": self.outcome,
            "source": self.source,
            "requested_by": self.requested_by_name or None,
            "requested_at": self.requested_at.isoformat(),
            "completed_at": self.completed_at.isoformat() if self.completed_at else None,
            "duration_ms": None if self.duration_ms is None else round(self.duration_ms, 2),
            "error": self.error,
            "run_id": self.run_id or None,
        }


class ParameterRecord(AppendOnlyRecord):
    """One parameter change (or refused attempt), append-only like TransitionRecord."""

    node = models.ForeignKey(
        "fleet.ManagedNode", verbose_name=gettext_lazy("node"), null=True, blank=True, on_delete=models.SET_NULL,
        related_name="parameter_changes"
    )
    robot_name = models.CharField(gettext_lazy("robot name"), max_length=63)
    node_name = models.CharField(gettext_lazy("node name"), max_length=255)
    name = models.CharField(gettext_lazy("parameter"), max_length=255)
    old_value = models.JSONField(gettext_lazy("old value"), null=True, blank=True)
    new_value = models.JSONField(gettext_lazy("new value"), null=True, blank=True)
    outcome = models.CharField(gettext_lazy("outcome"), max_length=16,
                               choices=[("succeeded", pgettext_lazy("outcome", "succeeded")),
                                                        ("rejected", pgettext_lazy("outcome", "rejected")),
                                                        ("observed", pgettext_lazy("outcome", "observed"))])
    reason = models.TextField(gettext_lazy("reason"), blank=True)
    source = models.CharField(gettext_lazy("source"), max_length=16, choices=TransitionRecord.Source.choices)
    at = models.DateTimeField(gettext_lazy("at"))
    fact_id = models.CharField(gettext_lazy("fact id"), max_length=32, null=True, blank=True, unique=True,
                               editable=False)
    run_id = models.CharField(gettext_lazy("run id"), max_length=64, blank=True,
                              help_text=gettext_lazy("The run (a mode's) that set it."))

    class Meta:
        ordering = ["-at", "-id"]
        indexes = [models.Index(fields=["node", "-at"], name="param_node_recent")]
        verbose_name = gettext_lazy("parameter record")
        verbose_name_plural = gettext_lazy("parameter records")

    def as_dict(self) -> dict:
        return {
            "id": self.id,
            "robot": self.robot_name,
            "node": self.node_name,
            "parameter": self.name,
            "old": self.old_value,
            "new": self.new_value,
            "outcome": self.outcome,
            "reason": self.reason,
            "source": self.source,
            "requested_by": self.requested_by_name or None,
            "at": self.at.isoformat(),
            "run_id": self.run_id or None,
        }


class ProcessRecord(AppendOnlyRecord):
    """One action on a robot's process through its supervisor (start, stop, restart), asked for
    or refused, or what the supervisor did by itself (an exit, a respawn, giving up)."""

    class Action(models.TextChoices):
        START = "start", pgettext_lazy("process action", "start")
        STOP = "stop", pgettext_lazy("process action", "stop")
        RESTART = "restart", pgettext_lazy("process action", "restart")
        EXITED = "exited", gettext_lazy("exited")
        RESPAWN = "respawn", gettext_lazy("respawned")
        GAVE_UP = "gave_up", gettext_lazy("respawning given up")

    class Source(models.TextChoices):
        DASHBOARD = "dashboard", pgettext_lazy("source", "dashboard")
        API = "api", "API"  # (the same word in every language)
        CLI = "cli", pgettext_lazy("source", "command line")
        SUPERVISOR = "supervisor", gettext_lazy("supervisor (by itself)")
        CONFIG = "config", gettext_lazy("profile changed")
        EXTERNAL = "external", pgettext_lazy("source", "external")

    profile = models.ForeignKey("fleet.ProcessProfile", null=True, blank=True, on_delete=models.SET_NULL,
                                related_name="records")
    robot_name = models.CharField(max_length=63)
    process_name = models.CharField(gettext_lazy("process"), max_length=64)
    supervisor = models.CharField(max_length=16, default="launch", help_text=gettext_lazy("What started the process."))
    action = models.CharField(max_length=16, choices=Action.choices)
    outcome = models.CharField(max_length=16, choices=[("succeeded", pgettext_lazy("outcome", "succeeded")),
                                                        ("failed", pgettext_lazy("outcome", "failed")),
                                                        ("rejected", pgettext_lazy("outcome", "rejected"))])
    source = models.CharField(max_length=16, choices=Source.choices)
    pid = models.PositiveIntegerField(null=True, blank=True)
    old_pid = models.PositiveIntegerField(null=True, blank=True)
    exit_code = models.IntegerField(null=True, blank=True)
    exit_signal = models.CharField(max_length=16, blank=True)
    message = models.TextField(blank=True)
    took_ms = models.FloatField(null=True, blank=True)
    at = models.DateTimeField()
    fact_id = models.CharField(max_length=32, null=True, blank=True, unique=True, editable=False)

    class Meta:
        ordering = ["-at", "-id"]
        indexes = [models.Index(fields=["robot_name", "-at"], name="process_robot_recent")]
        verbose_name = gettext_lazy("process record")
        verbose_name_plural = gettext_lazy("process records")

    def as_dict(self) -> dict:
        return {
            "id": self.id, "robot": self.robot_name, "process": self.process_name, "supervisor": self.supervisor,
            "action": self.action, "outcome": self.outcome, "source": self.source,
            "requested_by": self.requested_by_name or None, "pid": self.pid, "old_pid": self.old_pid,
            "exit_code": self.exit_code, "exit_signal": self.exit_signal or None, "message": self.message,
            "took_ms": self.took_ms, "at": self.at.isoformat(),
        }


class AccessDenial(models.Model):
    """A refused attempt: a change without the role for it, a bad token or session, a failed
    login. Kept for review by admins, bounded (audit/denials.py prunes the oldest)."""

    at = models.DateTimeField(gettext_lazy("at"), auto_now_add=True, db_index=True)
    user = models.ForeignKey(settings.AUTH_USER_MODEL, verbose_name=gettext_lazy("user"), null=True, blank=True,
                             on_delete=models.SET_NULL, related_name="+")
    username = models.CharField(gettext_lazy("username"), max_length=150, blank=True,
                                help_text=gettext_lazy("The account, or the name tried at login."))
    client = models.CharField(gettext_lazy("client"), max_length=64, blank=True,
                              help_text=gettext_lazy("The client's address as the site saw it."))
    method = models.CharField(gettext_lazy("method"), max_length=8)
    path = models.CharField(gettext_lazy("path"), max_length=300)
    status = models.PositiveSmallIntegerField(gettext_lazy("status"))
    code = models.CharField(
        gettext_lazy("code"), max_length=32,
        help_text="unauthorized, forbidden, csrf_failed, bad_token, login_failed, socket_origin"
    )
    detail = models.CharField(gettext_lazy("detail"), max_length=200, blank=True)

    class Meta:
        ordering = ["-at"]
        verbose_name = gettext_lazy("refused attempt")
        verbose_name_plural = gettext_lazy("refused attempts")

    def __str__(self) -> str:
        return f"{self.at:%Y-%m-%d %H:%M:%S} {self.code} {self.username or self.client} {self.method} {self.path}"
