"""The robots' health as their nodes report it on /diagnostics and /diagnostics_agg: the latest
status per name (level, message, key/values, when last heard, stale or not) and, per status, its
history of level changes. Written by the ingest process (ingest/diagnostic_facts.py) only."""
from __future__ import annotations

from django.db import models
from django.utils.translation import gettext_lazy

from ros_gateway.shared import protocol

OK, WARN, ERROR, STALE = 0, 1, 2, 3
LEVEL_WORDS = {OK: "OK", WARN: "WARN", ERROR: "ERROR", STALE: "STALE"}
MAX_HISTORY = 200  # level changes kept per status (older ones are deleted as new ones come)


def page_group(robot_id: int) -> str:
    """The Channels group of a robot's open diagnostics pages (told which statuses changed)."""
    return f"diagnostics.{robot_id}"


class Status(models.Model):
    robot = models.ForeignKey("fleet.Robot", on_delete=models.CASCADE, related_name="diagnostic_statuses")
    name = models.CharField(max_length=protocol.MAX_STATUS_NAME)
    level = models.PositiveSmallIntegerField(default=OK)  # as reported (0-3)
    stale = models.BooleanField(default=False)  # not heard for the stale time (the gateway says)
    message = models.CharField(max_length=protocol.MAX_STATUS_MESSAGE, blank=True)
    hardware_id = models.CharField(max_length=protocol.MAX_HARDWARE_ID, blank=True)
    values = models.JSONField(default=list)  # [[key, value], ...]
    topic = models.CharField(max_length=300, blank=True)
    node = models.CharField(max_length=300, blank=True)  # the node reporting it, where known
    heard = models.DateTimeField()  # last update from the robot
    level_since = models.DateTimeField()  # the shown level (stale included) since
    # Since when it has been at least WARN / at least ERROR / stale, without a break (the alert rules').
    warn_since = models.DateTimeField(null=True, blank=True)
    error_since = models.DateTimeField(null=True, blank=True)
    stale_since = models.DateTimeField(null=True, blank=True)

    class Meta:
        constraints = [models.UniqueConstraint(fields=["robot", "name"], name="diagnostic_status_once")]
        ordering = ["robot", "name"]
        verbose_name = gettext_lazy("status")
        verbose_name_plural = gettext_lazy("statuss")

    def __str__(self) -> str:
        return f"{self.name} ({self.word})"

    @property
    def shown(self) -> int:
        """The level to show: stale (whatever it last said) when not heard."""
        return STALE if self.stale else self.level

    @property
    def word(self) -> str:
        return LEVEL_WORDS.get(self.shown, "ERROR")

    def as_dict(self) -> dict:
        return {"name": self.name, "level": LEVEL_WORDS.get(self.level, "ERROR"), "shown": self.word,
                "stale": self.stale, "message": self.message, "hardware_id": self.hardware_id,
                "values": self.values, "topic": self.topic, "node": self.node or None,
                "heard": self.heard.isoformat(), "level_since": self.level_since.isoformat()}


class LevelChange(models.Model):
    """A status's shown level changed (stale included): its history."""

    robot = models.ForeignKey("fleet.Robot", on_delete=models.CASCADE, related_name="+")
    name = models.CharField(max_length=protocol.MAX_STATUS_NAME)
    level = models.PositiveSmallIntegerField()  # shown level: 0-3 (3: stale or STALE)
    message = models.CharField(max_length=protocol.MAX_STATUS_MESSAGE, blank=True)
    at = models.DateTimeField()

    class Meta:
        indexes = [models.Index(fields=["robot", "name", "at"], name="diagnostic_history")]
        ordering = ["-at", "-id"]
        verbose_name = gettext_lazy("level change")
        verbose_name_plural = gettext_lazy("level changes")

    def as_dict(self) -> dict:
        return {"at": self.at.isoformat(), "level": LEVEL_WORDS.get(self.level, "ERROR"), "message": self.message}


class Intake(models.Model):
    """What was left out of a robot's diagnostics (over the bounds), counted."""

    robot = models.OneToOneField("fleet.Robot", primary_key=True, on_delete=models.CASCADE,
                                 related_name="diagnostics_intake")
    left_out_by_gateway = models.PositiveBigIntegerField(default=0)  # over the gateway's statuses per robot
    left_out_here = models.PositiveBigIntegerField(default=0)  # over the site's statuses per robot

    class Meta:
        verbose_name = gettext_lazy("intake")
        verbose_name_plural = gettext_lazy("intakes")
