"""Launch profiles: a robot's processes that its gateway starts and looks after (the gateway as
the robot's supervisor: ros_gateway/supervisor.py), registered by an admin. What the gateway
last reported of each (running, its pid, exits, respawns) is kept beside the profile.

Imported by fleet/models.py, so Django registers the model with the fleet app."""
from __future__ import annotations

import signal

from django.core.validators import MaxValueValidator, MinValueValidator, RegexValidator
from django.db import models
from django.utils.translation import gettext_lazy

PROCESS_NAME = RegexValidator(r"^[A-Za-z0-9_.-]{1,64}$", gettext_lazy("1-64 letters, digits, '_', '.' or '-'."))
STOP_SIGNALS = [(signal.SIGTERM.name, "SIGTERM"), (signal.SIGINT.name, gettext_lazy("SIGINT (as Ctrl-C; ros2 launch)"))]


class ProcessProfile(models.Model):
    class Status(models.TextChoices):  # (the labels: the Processes page's and the CLI's words)
        UNKNOWN = "unknown", gettext_lazy("not reported yet")
        STARTING = "starting", gettext_lazy("starting")
        RUNNING = "running", gettext_lazy("running")
        STOPPING = "stopping", gettext_lazy("stopping")
        STOPPED = "stopped", gettext_lazy("stopped")
        EXITED = "exited", gettext_lazy("exited")
        BACKING_OFF = "backing_off", gettext_lazy("exited, starting again soon")
        GIVEN_UP = "given_up", gettext_lazy("given up (kept failing)")

    robot = models.ForeignKey("fleet.Robot", verbose_name=gettext_lazy("robot"), on_delete=models.CASCADE,
                              related_name="process_profiles")
    name = models.CharField(gettext_lazy("name"), max_length=64, validators=[PROCESS_NAME],
                            help_text=gettext_lazy("How operators and the audit log name the process, e.g. 'drivers'."))
    command = models.CharField(gettext_lazy("command"), max_length=4096,
                               help_text=gettext_lazy("The executable: an absolute path or a name on the gateway's "
                                                      "PATH (e.g. ros2, python3)."))
    args = models.JSONField(gettext_lazy("arguments"), default=list, blank=True,
                            help_text=gettext_lazy('A JSON list of strings, e.g. ["launch", "agv_bringup", '
                                                   '"drivers.launch.py"].'))
    env = models.JSONField(gettext_lazy("environment"), default=dict, blank=True,
                           help_text=gettext_lazy("Added to the gateway's environment, shown to admins: "
                                                  '{"ROS_DOMAIN_ID": "21"}.'))
    secret_env = models.JSONField(gettext_lazy("secret environment"), default=dict, blank=True, editable=False,
                                  help_text=gettext_lazy("Values never shown again once saved (tokens, passwords)."))
    cwd = models.CharField(gettext_lazy("working directory"), max_length=4096, blank=True)
    enabled = models.BooleanField(gettext_lazy("enabled"), default=True,
                                  help_text=gettext_lazy("Started by the gateway; off: registered, not run."))
    respawn = models.BooleanField(gettext_lazy("respawn"), default=True,
                                  help_text=gettext_lazy("Started again when it exits without being asked to."))
    respawn_delay_s = models.FloatField(gettext_lazy("respawn delay s"), default=1.0,
                                        validators=[MinValueValidator(0.0), MaxValueValidator(300.0)],
                                        help_text=gettext_lazy("Before the first respawn; doubles while it keeps "
                                                               "exiting at once."))
    max_failures = models.PositiveIntegerField(gettext_lazy("max failures"), default=5,
                                               validators=[MinValueValidator(1), MaxValueValidator(100)],
                                               help_text=gettext_lazy("Exits within the window after which it is not "
                                                                      "respawned."))
    failure_window_s = models.FloatField(gettext_lazy("failure window s"), default=300.0,
                                         validators=[MinValueValidator(1.0), MaxValueValidator(86400.0)])
    stop_signal = models.CharField(gettext_lazy("stop signal"), max_length=8, choices=STOP_SIGNALS,
                                   default=signal.SIGINT.name)
    stop_grace_s = models.FloatField(gettext_lazy("stop grace s"), default=10.0,
                                     validators=[MinValueValidator(0.0), MaxValueValidator(300.0)],
                                     help_text=gettext_lazy("After the stop signal, before SIGKILL."))

    # As last reported by the gateway (ingest/process_facts.py); never edited.
    status = models.CharField(gettext_lazy("status"), max_length=16, choices=Status.choices, default=Status.UNKNOWN,
                              editable=False)
    pid = models.PositiveIntegerField(gettext_lazy("pid"), null=True, blank=True, editable=False)
    status_since = models.DateTimeField(gettext_lazy("status since"), null=True, blank=True, editable=False)
    restarts = models.PositiveIntegerField(gettext_lazy("restarts"), default=0, editable=False)
    last_exit_code = models.IntegerField(gettext_lazy("last exit code"), null=True, blank=True, editable=False)
    last_exit_signal = models.CharField(gettext_lazy("last exit signal"), max_length=16, blank=True, editable=False)
    last_exit_at = models.DateTimeField(gettext_lazy("last exit at"), null=True, blank=True, editable=False)
    last_message = models.TextField(gettext_lazy("last message"), blank=True, editable=False)

    class Meta:
        ordering = ["robot__name", "name"]
        constraints = [models.UniqueConstraint(fields=["robot", "name"], name="process_name_per_robot")]
        verbose_name = gettext_lazy("launch profile")
        verbose_name_plural = gettext_lazy("launch profiles")

    def __str__(self) -> str:
        return f"{self.name} on {self.robot.name}" if self.robot_id else self.name

    def command_line(self) -> str:
        """What operators see of the command (never the environment)."""
        return " ".join([self.command, *(str(a) for a in self.args or [])])

    def for_gateway(self) -> dict:
        """The profile as the gateway reads it (ros_gateway.launch_profile.LaunchProfile.from_config)."""
        return {
            "name": self.name, "command": self.command, "args": list(self.args or []),
            "env": {**(self.env or {}), **(self.secret_env or {})}, "cwd": self.cwd or None,
            "respawn": self.respawn, "respawn_delay": self.respawn_delay_s, "stop_signal": self.stop_signal,
            "stop_grace": self.stop_grace_s, "max_failures": self.max_failures,
            "failure_window": self.failure_window_s,
        }

    def as_dict(self) -> dict:
        return {
            "robot": self.robot.name, "name": self.name, "supervisor": "launch", "command": self.command_line(),
            "enabled": self.enabled,
            "respawn": self.respawn, "status": self.status, "pid": self.pid,
            "since": self.status_since.isoformat() if self.status_since else None, "restarts": self.restarts,
            "last_exit": None if self.last_exit_at is None else {
                "code": self.last_exit_code, "signal": self.last_exit_signal or None,
                "at": self.last_exit_at.isoformat()},
            "message": self.last_message,
        }
