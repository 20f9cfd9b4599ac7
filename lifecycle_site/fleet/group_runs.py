"""Group runs: one ordered group operation on a robot's nodes (a model of the fleet app, kept
apart from fleet/models.py for its size; imported there, so ``fleet.models.GroupRun`` stays)."""
from __future__ import annotations

from django.conf import settings
from django.db import models
from django.utils.translation import gettext_lazy

from lifecycle_site.fleet.models import Robot
from ros_gateway.shared import operations


class GroupRun(models.Model):
    """One ordered group operation on a robot's nodes (bring up, pause, ..., restart)."""

    class Policy(models.TextChoices):
        STOP = "stop", gettext_lazy("stop at the first failure")
        CONTINUE = "continue", gettext_lazy("continue and report")

    class Status(models.TextChoices):
        # (the labels: the CLI's words for a run's status)
        QUEUED = "queued", gettext_lazy("queued")
        RUNNING = "running", gettext_lazy("running")
        SUCCEEDED = "succeeded", gettext_lazy("succeeded")
        FAILED = "failed", gettext_lazy("failed")
        PARTIAL = "partial", gettext_lazy("partly failed")

    ENDED = (Status.SUCCEEDED, Status.FAILED, Status.PARTIAL)  # a verdict: final

    id = models.CharField(primary_key=True, max_length=32, editable=False)
    robot = models.ForeignKey(Robot, on_delete=models.CASCADE, related_name="runs")
    # Read from the shared table when asked: a new operation needs no migration.
    operation = models.CharField(max_length=16, choices=operations.choices)
    policy = models.CharField(max_length=16, choices=Policy.choices, default=Policy.STOP)
    node_timeout = models.FloatField(default=5.0)
    only_nodes = models.JSONField(default=list, blank=True,
                                  help_text=gettext_lazy("Node names; empty for all of the robot's."))
    plan = models.JSONField(default=dict, blank=True,
                            help_text=gettext_lazy("A mode's run: the mode, each node's target state and parameters."))
    steps = models.PositiveSmallIntegerField(
        null=True, blank=True, editable=False,
        help_text=gettext_lazy("How many steps of the robot's bring-up order the run went in (1: all side by side); "
                               "empty for a run the gateway started itself (a recovery)."))
    status = models.CharField(max_length=16, choices=Status.choices, default=Status.QUEUED)
    message = models.TextField(blank=True)
    results = models.JSONField(default=list, blank=True)
    source = models.CharField(max_length=16, default="api")
    requested_by = models.ForeignKey(
        settings.AUTH_USER_MODEL, null=True, blank=True, on_delete=models.SET_NULL, related_name="+"
    )
    created = models.DateTimeField(auto_now_add=True)
    started = models.DateTimeField(null=True, blank=True)
    finished = models.DateTimeField(null=True, blank=True)

    class Meta:
        ordering = ["-created"]
        verbose_name = gettext_lazy("group run")
        verbose_name_plural = gettext_lazy("group runs")

    def __str__(self) -> str:
        return f"{self.get_operation_display()} {self.robot.name} ({self.status})"

    @property
    def done(self) -> bool:
        return self.status in self.ENDED

    def as_dict(self) -> dict:
        return {
            "id": self.id,
            "robot": self.robot.name,
            "operation": self.operation,
            "policy": self.policy,
            "node_timeout": self.node_timeout,
            "nodes": self.only_nodes,
            **({"mode": self.plan.get("mode")} if self.plan.get("mode") else {}),
            "steps": self.steps,
            "status": self.status,
            "message": self.message,
            "results": self.results,
            "source": self.source,
            "requested_by": self.requested_by.get_username() if self.requested_by else None,
            "created": self.created.isoformat(),
            "started": self.started.isoformat() if self.started else None,
            "finished": self.finished.isoformat() if self.finished else None,
        }
