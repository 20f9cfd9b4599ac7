"""Robot modes: each names, per node, a target state (or none: left alone) and parameter values.
A mode is one robot's, or a template shared by several robots with the same node names. One mode
per robot is current: the one last applied, whose targets are then its nodes' desired states."""
from __future__ import annotations

from django.conf import settings
from django.core.validators import RegexValidator
from django.db import models
from django.utils.translation import gettext_lazy

from lifecycle_site.modes import definitions

MODE_NAME_VALIDATOR = RegexValidator(
    definitions.MODE_NAME, gettext_lazy("Use lower-case letters, digits, '-' and '_' (for example production)."))


class Mode(models.Model):
    name = models.CharField(gettext_lazy("name"), max_length=63, unique=True, validators=[MODE_NAME_VALIDATOR])
    description = models.TextField(gettext_lazy("description"), blank=True)
    robots = models.ManyToManyField("fleet.Robot", verbose_name=gettext_lazy("robots"), related_name="modes",
                                    blank=True,
                                    help_text=gettext_lazy("The robots it is for: one, or several with the same node "
                                                           "names."))
    nodes = models.JSONField(
        gettext_lazy("nodes"), default=dict, blank=True, validators=[definitions.validate_nodes],
        help_text=gettext_lazy('Per node: {"/lidar_driver": {"state": "active", "parameters": {"scan_rate_hz": 8.0}}}; '
                               'state null (or no state) leaves the node where it is.'))
    ready_when = models.JSONField(
        gettext_lazy("ready when"), default=list, blank=True, validators=[definitions.validate_readiness],
        help_text=gettext_lazy('All must hold for the mode to be ready, e.g. [{"node": "/lidar_driver", "state": '
                               '"active"}, {"node": "/lidar_driver", "parameter": "scan_rate_hz", "min": 5, "max": '
                               '20}, {"topic": "/scan", "min_hz": 5, "window_s": 5}]; the topic rates are measured by '
                               'the gateway.'))
    updated = models.DateTimeField(gettext_lazy("updated"), auto_now=True)
    updated_by = models.ForeignKey(settings.AUTH_USER_MODEL, verbose_name=gettext_lazy("updated by"), null=True,
                                   blank=True, on_delete=models.SET_NULL, related_name="+", editable=False)

    class Meta:
        ordering = ["name"]
        verbose_name = gettext_lazy("mode")
        verbose_name_plural = gettext_lazy("modes")

    def __str__(self) -> str:
        return self.name

    def targets(self) -> dict[str, str | None]:
        return {name: entry.get("state") for name, entry in self.nodes.items()}

    def parameters(self) -> dict[str, dict]:
        return {name: dict(entry["parameters"]) for name, entry in self.nodes.items() if entry.get("parameters")}

    def as_dict(self) -> dict:
        return {"name": self.name, "description": self.description, "nodes": self.nodes, "ready_when": self.ready_when,
                "robots": sorted(self.robots.values_list("name", flat=True)),
                "updated": self.updated.isoformat() if self.updated else None}


class CurrentMode(models.Model):
    """The mode a robot is in: the last one applied to it (by whom, when, with which run)."""

    robot = models.OneToOneField("fleet.Robot", verbose_name=gettext_lazy("robot"), primary_key=True,
                                 on_delete=models.CASCADE, related_name="current_mode")
    mode = models.ForeignKey(Mode, verbose_name=gettext_lazy("mode"), on_delete=models.CASCADE,
                             related_name="current_on")
    since = models.DateTimeField(gettext_lazy("since"))
    applied_by = models.ForeignKey(settings.AUTH_USER_MODEL, verbose_name=gettext_lazy("applied by"), null=True,
                                   blank=True, on_delete=models.SET_NULL, related_name="+")
    run = models.ForeignKey("fleet.GroupRun", verbose_name=gettext_lazy("run"), null=True, blank=True,
                            on_delete=models.SET_NULL, related_name="+")
    not_ready_since = models.DateTimeField(gettext_lazy("not ready since"), null=True, blank=True,
                                           help_text=gettext_lazy("Since when a readiness predicate fails."))

    class Meta:
        verbose_name = gettext_lazy("current mode")
        verbose_name_plural = gettext_lazy("current modes")

    def __str__(self) -> str:
        return f"{self.robot} in {self.mode}"

    def topics(self) -> list[dict]:
        """What the gateway measures for its readiness: [{"topic", "window_s"}]."""
        return [{"topic": p["topic"], "window_s": float(p.get("window_s", 5.0))}
                for p in self.mode.ready_when if isinstance(p, dict) and "topic" in p]


class TopicRate(models.Model):
    """How often a topic of a robot is published, as its gateway measured it last (for readiness)."""

    robot = models.ForeignKey("fleet.Robot", on_delete=models.CASCADE, related_name="topic_rates")
    topic = models.CharField(max_length=255)
    hz = models.FloatField(null=True, blank=True, help_text=gettext_lazy("Empty: no publisher found."))
    window_s = models.FloatField()
    at = models.DateTimeField()

    class Meta:
        constraints = [models.UniqueConstraint(fields=["robot", "topic"], name="one_rate_per_robot_topic")]
        verbose_name = gettext_lazy("topic rate")
        verbose_name_plural = gettext_lazy("topic rates")
