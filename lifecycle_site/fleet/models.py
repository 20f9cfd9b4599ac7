"""Gateways, the robots each of them watches, their managed nodes and /rosout history (group runs:
group_runs.py, launch profiles: process_profiles.py)."""
from __future__ import annotations

from django.core.validators import MaxValueValidator, MinValueValidator, RegexValidator
from django.db import models
from django.utils.translation import gettext_lazy, pgettext_lazy

from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm

ROBOT_NAME_VALIDATOR = RegexValidator(
    r"^[a-z0-9][a-z0-9_-]{0,62}$",
    gettext_lazy("Use lower-case letters, digits, '-' and '_' (for example agv-1)."),
)
NAMESPACE_VALIDATOR = RegexValidator(
    r"^(/[A-Za-z_][A-Za-z0-9_]*)*$",
    gettext_lazy("A ROS namespace such as /agv1 or /plant/agv1, or empty for the whole domain."),
)

GATEWAY_NAME_VALIDATOR = RegexValidator(
    protocol.GATEWAY_NAME_RE,
    gettext_lazy("Use lower-case letters, digits, '-' and '_', starting with a letter or digit (for example cell-a)."),
)


class Gateway(models.Model):
    """A ROS gateway process (one per cell, network or device) and what it last reported.

    The site registers it (``manage.py add_gateway``); the ingest process copies its heartbeat
    here and keeps the accounts of its fact and log streams. Whether it is online right now
    comes from its heartbeat in Redis (``gateway_link.gateways.status``), not from this row.
    """

    name = models.CharField(gettext_lazy("name"), max_length=63, unique=True, validators=[GATEWAY_NAME_VALIDATOR])
    description = models.TextField(gettext_lazy("description"), blank=True)
    created = models.DateTimeField(gettext_lazy("created"), auto_now_add=True)
    # Its Redis user's password, hashed as Redis's ACL takes it; the password itself is shown once.
    redis_password_sha256 = models.CharField(gettext_lazy("redis password sha256"), max_length=64, blank=True,
                                             editable=False)
    # From its heartbeat (copied by the ingest process).
    last_beat = models.DateTimeField(gettext_lazy("last beat"), null=True, blank=True)
    started = models.DateTimeField(gettext_lazy("started"), null=True, blank=True)
    stopped = models.BooleanField(gettext_lazy("stopped"), default=False,
                                  help_text=gettext_lazy("Its last heartbeat said it stopped cleanly."))
    instance = models.CharField(gettext_lazy("instance"), max_length=32, blank=True,
                                help_text=gettext_lazy("Id of its running process."))
    version = models.CharField(gettext_lazy("version"), max_length=64, blank=True)
    host = models.CharField(gettext_lazy("host"), max_length=255, blank=True)
    pid = models.PositiveIntegerField(gettext_lazy("pid"), null=True, blank=True)
    domains = models.JSONField(gettext_lazy("ROS domains"), default=list, blank=True)
    dds = models.JSONField(gettext_lazy("DDS discovery settings"), default=dict, blank=True)
    node_count = models.PositiveIntegerField(gettext_lazy("nodes"), default=0)
    outbox = models.JSONField(gettext_lazy("outbox"), default=dict, blank=True,
                              help_text=gettext_lazy("What it held or dropped while Redis was away."))
    # Kept by the ingest process.
    backlog = models.PositiveIntegerField(gettext_lazy("backlog"), default=0,
                                          help_text=gettext_lazy("Entries of its streams not yet stored."))
    facts_lost = models.PositiveBigIntegerField(
        gettext_lazy("facts lost"), default=0, help_text=gettext_lazy("Facts trimmed from Redis before they were read.")
    )
    facts_rejected = models.PositiveBigIntegerField(gettext_lazy("facts rejected"), default=0,
                                                    help_text=gettext_lazy("Facts the site could not apply."))
    logs_lost = models.PositiveBigIntegerField(gettext_lazy("logs lost"), default=0,
                                               help_text=gettext_lazy("Log batches trimmed before they were read."))
    logs_dropped = models.PositiveBigIntegerField(gettext_lazy("logs dropped"), default=0,
                                                  help_text=gettext_lazy("Log records its buffer dropped."))
    logs_received = models.PositiveBigIntegerField(gettext_lazy("logs received"), default=0,
                                                   help_text=gettext_lazy("Log records stored from it."))
    facts_cursor = models.CharField(gettext_lazy("facts cursor"), max_length=40, blank=True,
                                    help_text=gettext_lazy("Last applied entry of its facts stream."))
    logs_cursor = models.CharField(gettext_lazy("logs cursor"), max_length=40, blank=True,
                                   help_text=gettext_lazy("Last stored entry of its logs stream."))
    facts_instance = models.CharField(gettext_lazy("facts instance"), max_length=32, blank=True)
    facts_seq = models.PositiveBigIntegerField(gettext_lazy("facts seq"), default=0)
    logs_instance = models.CharField(gettext_lazy("logs instance"), max_length=32, blank=True)
    logs_seq = models.PositiveBigIntegerField(gettext_lazy("logs seq"), default=0)
    # Kept by the site's checks of what the gateway sends and holds (gateway_link/quarantine.py).
    quarantined = models.DateTimeField(
        gettext_lazy("quarantined"), null=True, blank=True, editable=False,
        help_text=gettext_lazy("When the site cut it off (its Redis user disabled, its streams no longer read); "
                               "empty while it may work."),
    )
    quarantine_reason = models.TextField(gettext_lazy("quarantine reason"), blank=True, editable=False)
    quarantines = models.PositiveIntegerField(gettext_lazy("quarantines"), default=0, editable=False,
                                              help_text=gettext_lazy("How often it was cut off."))
    live_refused = models.PositiveBigIntegerField(gettext_lazy("live refused"), default=0,
                                                  help_text=gettext_lazy("Live updates the site refused."))
    redis_bytes = models.PositiveBigIntegerField(
        gettext_lazy("redis bytes"), default=0, editable=False,
        help_text=gettext_lazy("What its Redis keys held at the site's last count."))

    class Meta:
        ordering = ["name"]
        verbose_name = gettext_lazy("gateway")
        verbose_name_plural = gettext_lazy("gateways")

    def __str__(self) -> str:
        return self.name

    @property
    def redis_user(self) -> str:
        return f"gw-{self.name}"


def default_gateway_id() -> int:
    """Robots belong to the gateway ``local`` unless told otherwise (made on first need)."""
    found = Gateway.objects.filter(name=protocol.DEFAULT_GATEWAY).values_list("pk", flat=True).first()
    if found is None:
        found = Gateway.objects.create(
            name=protocol.DEFAULT_GATEWAY, description="The gateway on the site's own machine."
        ).pk
    return found


KEEP_CHOICES = [(policy, policy) for policy in protocol.KEEP_POLICIES]


class Robot(models.Model):
    """A robot is a ROS domain, optionally narrowed to a namespace within it."""

    name = models.CharField(gettext_lazy("name"), max_length=63, unique=True, validators=[ROBOT_NAME_VALIDATOR])
    domain_id = models.PositiveSmallIntegerField(
        gettext_lazy("ROS domain id"),
        validators=[MinValueValidator(0), MaxValueValidator(232)],
        help_text=gettext_lazy("ROS_DOMAIN_ID the robot's nodes use (0-232)."),
    )
    namespace = models.CharField(
        gettext_lazy("namespace"), max_length=200,
        blank=True,
        validators=[NAMESPACE_VALIDATOR],
        help_text=gettext_lazy("Only nodes under this namespace belong to the robot; empty for all of the domain."),
    )
    gateway = models.ForeignKey(
        Gateway, verbose_name=gettext_lazy("gateway"),
        on_delete=models.PROTECT,
        related_name="robots",
        default=default_gateway_id,
        help_text=gettext_lazy("The gateway that reaches this robot's ROS domain."),
    )
    description = models.TextField(gettext_lazy("description"), blank=True)
    enabled = models.BooleanField(gettext_lazy("enabled"), default=True,
                                  help_text=gettext_lazy("The gateway watches enabled robots only."))
    auto_recover = models.BooleanField(
        gettext_lazy("auto recover"), default=False,
        help_text=gettext_lazy("When a node comes back after its process was restarted, drive it to its desired "
                               "state."),
    )
    keep_desired = models.CharField(
        gettext_lazy("keep desired states"), max_length=8, default="off", choices=KEEP_CHOICES,
        help_text=gettext_lazy("When another tool moves a node away from its desired state: nothing (off), an alert, "
                               "or the gateway drives it back (enforce; it stops and says so when another manager "
                               "keeps moving it)."))
    created = models.DateTimeField(gettext_lazy("created"), auto_now_add=True)

    class Meta:
        ordering = ["name"]
        verbose_name = gettext_lazy("robot")
        verbose_name_plural = gettext_lazy("robots")

    def __str__(self) -> str:
        return self.name

    def owns(self, node_name: str) -> bool:
        """Whether a fully qualified node name lies under this robot's namespace."""
        return not self.namespace or node_name.startswith(self.namespace.rstrip("/") + "/")


class ManagedNode(models.Model):
    """A lifecycle node seen on a robot (or pinned by name before it shows up)."""

    robot = models.ForeignKey(Robot, verbose_name=gettext_lazy("robot"), on_delete=models.CASCADE, related_name="nodes")
    name = models.CharField(gettext_lazy("fully qualified name"), max_length=255)
    key = models.CharField(gettext_lazy("key"), max_length=320, unique=True, editable=False)
    state_id = models.PositiveSmallIntegerField(gettext_lazy("state id"), default=sm.UNKNOWN)
    state_label = models.CharField(gettext_lazy("state label"), max_length=32, default="unknown")
    alive = models.BooleanField(gettext_lazy("alive"), default=False)
    gone_reason = models.CharField(
        gettext_lazy("gone reason"), max_length=16, blank=True, default="",
        help_text=gettext_lazy("Why a node that is not alive went: 'process_lost' (its process ended, or its node "
                               "left the ROS graph), 'unreachable' (its process stopped answering the gateway's "
                               "probes: its host or link may be down), or empty (not known, or its robot is no "
                               "longer watched)."),
    )
    process_status = models.CharField(
        gettext_lazy("process status"), max_length=16, blank=True, default="",
        choices=[("", "-"), ("lost", pgettext_lazy("node process", "lost")),
                 ("restarted", pgettext_lazy("node process", "restarted"))],
        help_text=gettext_lazy("What was last seen of the node's process: lost, or restarted (a new instance)."),
    )
    process_since = models.DateTimeField(gettext_lazy("process since"), null=True, blank=True,
                                         help_text=gettext_lazy("When that was seen."))
    supervised_by = models.CharField(
        gettext_lazy("supervised by"), max_length=64, blank=True, editable=False,
        help_text=gettext_lazy("The launch profile whose process runs this node, as its gateway last saw ('' none "
                               "known)."),
    )
    first_seen = models.DateTimeField(gettext_lazy("first seen"), null=True, blank=True)
    last_seen = models.DateTimeField(gettext_lazy("last seen"), null=True, blank=True)
    state_changed = models.DateTimeField(gettext_lazy("state changed"), null=True, blank=True)
    # The audit chain (ingest/state_chain.py): the state the node's records leave it in, as of
    # when, and since when the node has been seen in another state that no record explains yet.
    audited_state_id = models.PositiveSmallIntegerField(gettext_lazy("audited state id"), null=True, blank=True,
                                                        editable=False)
    audited_at = models.DateTimeField(gettext_lazy("audited at"), null=True, blank=True, editable=False)
    unexplained_since = models.DateTimeField(gettext_lazy("unexplained since"), null=True, blank=True, editable=False)
    order = models.PositiveIntegerField(
        gettext_lazy("order"), null=True,
        blank=True,
        help_text=gettext_lazy("Position in the robot's bring-up order, lowest first; nodes sharing a position go "
                               "together. Empty: after the others, side by side with the other unordered nodes."),
    )
    desired_state = models.CharField(
        gettext_lazy("desired state"), max_length=16,
        blank=True,
        choices=[("", pgettext_lazy("desired state", "none")), *((label, label) for label in sm.DESIRED_STATES)],
        help_text=gettext_lazy("The state automatic recovery brings this node back to after a restart of its "
                               "process."),
    )
    keep_desired = models.CharField(
        gettext_lazy("keep desired state"), max_length=8, blank=True,
        choices=[("", gettext_lazy("as its robot")), *KEEP_CHOICES],
        help_text=gettext_lazy("Whether its desired state is kept against other tools; empty: as its robot says."))
    # Set when the gateway stopped keeping it (another manager keeps moving it); cleared by an operator.
    enforcement_stopped = models.DateTimeField(gettext_lazy("enforcement stopped"), null=True, blank=True,
                                               editable=False)
    enforcement_note = models.TextField(gettext_lazy("enforcement note"), blank=True, editable=False)
    enforcement_resumed = models.DateTimeField(gettext_lazy("enforcement resumed"), null=True, blank=True,
                                               editable=False)  # tells the gateway

    class Meta:
        ordering = ["robot__name", "name"]
        constraints = [models.UniqueConstraint(fields=["robot", "name"], name="unique_node_per_robot")]
        permissions = [("operate_node", "Can trigger lifecycle transitions")]
        verbose_name = gettext_lazy("managed node")
        verbose_name_plural = gettext_lazy("managed nodes")

    def __str__(self) -> str:
        return f"{self.robot.name}:{self.name}"

    def save(self, *args, **kwargs) -> None:
        self.key = protocol.node_key(self.robot.name, self.name)
        super().save(*args, **kwargs)

    @property
    def state(self) -> dict:
        return {"id": self.state_id, "label": self.state_label}

    @property
    def keep(self) -> str:
        """Its policy as the gateway follows it: its own or its robot's; "paused" after a fight."""
        policy = self.keep_desired or self.robot.keep_desired
        return protocol.KEEP_PAUSED if policy == "enforce" and self.enforcement_stopped else policy

    @property
    def valid_transitions(self) -> list[dict]:
        if not self.alive:
            return []
        return [t.as_dict() for t in sm.valid_transitions(self.state_id)]


class NodeAbsence(models.Model):
    """A stretch of time a node that had been seen was not running: from the gateway's node.gone
    (or its robot's node list without it) to the node's return (node.seen, or the list again).

    The state timeline draws these; ManagedNode keeps only the current absence. Pruned by the
    ingest process after ABSENCE_KEEP_DAYS (longer than the widest timeline window)."""

    REASONS = [("", pgettext_lazy("node absence", "left")), ("process_lost", gettext_lazy("process lost")),
               ("unreachable", pgettext_lazy("node status", "unreachable"))]

    node = models.ForeignKey(ManagedNode, verbose_name=gettext_lazy("node"), on_delete=models.CASCADE,
                             related_name="absences")
    gone_at = models.DateTimeField(gettext_lazy("gone at"))
    back_at = models.DateTimeField(gettext_lazy("back at"), null=True, blank=True,
                                   help_text=gettext_lazy("Empty while the node is still away."))
    reason = models.CharField(gettext_lazy("reason"), max_length=16, blank=True, default="", choices=REASONS)

    class Meta:
        ordering = ["-gone_at"]
        indexes = [models.Index(fields=["node", "-gone_at"], name="absence_node_recent")]
        constraints = [
            # At most one open absence per node: a node.gone applied twice opens it once.
            models.UniqueConstraint(fields=["node"], condition=models.Q(back_at__isnull=True),
                                    name="one_open_absence_per_node"),
        ]
        verbose_name = gettext_lazy("node absence")
        verbose_name_plural = gettext_lazy("node absences")

    def __str__(self) -> str:
        return f"{self.node} away from {self.gone_at:%Y-%m-%d %H:%M:%S}"


class GatewayOutage(models.Model):
    """A stretch of time a gateway could take no commands, and nothing received its robots'
    /rosout: from its last heartbeat before the site saw it offline, stopped or quarantined (or
    before its process was restarted), to the first heartbeat after (ingest/outages.py, kept by the
    ingest process). The state timeline and the log consoles mark them. Pruned like absences."""

    gateway = models.ForeignKey(Gateway, on_delete=models.CASCADE, related_name="outages")
    began = models.DateTimeField()
    ended = models.DateTimeField(null=True, blank=True, help_text=gettext_lazy("Empty while it lasts."))
    reason = models.CharField(max_length=16, blank=True, default="", help_text="offline, stopped or quarantined")

    class Meta:
        ordering = ["-began"]
        indexes = [models.Index(fields=["gateway", "-began"], name="outage_gateway_recent")]
        constraints = [
            models.UniqueConstraint(fields=["gateway"], condition=models.Q(ended__isnull=True),
                                    name="one_open_outage_per_gateway"),
        ]
        verbose_name = gettext_lazy("gateway outage")
        verbose_name_plural = gettext_lazy("gateway outages")

    def __str__(self) -> str:
        return f"{self.gateway} {self.reason or 'offline'} from {self.began:%Y-%m-%d %H:%M:%S}"

    def as_dict(self) -> dict:
        return {"id": self.id, "gateway": self.gateway.name, "began": self.began.isoformat(),
                "ended": self.ended.isoformat() if self.ended else None, "reason": self.reason}


class LogRecord(models.Model):
    """One /rosout message. Pruned by the ingest process to a bounded count and age."""

    DEBUG, INFO, WARN, ERROR, FATAL = 10, 20, 30, 40, 50
    LEVELS = [(DEBUG, "DEBUG"), (INFO, "INFO"), (WARN, "WARN"), (ERROR, "ERROR"), (FATAL, "FATAL")]

    # No index of their own: the indexes below begin with them (each index is written with
    # every record, and a log flood writes 20,000 a second).
    robot = models.ForeignKey(Robot, on_delete=models.CASCADE, related_name="log_records", db_index=False)
    node = models.ForeignKey(
        ManagedNode, null=True, blank=True, on_delete=models.SET_NULL, related_name="log_records", db_index=False
    )
    logger = models.CharField(max_length=255)
    stamp = models.DateTimeField()
    level = models.PositiveSmallIntegerField(choices=LEVELS)
    message = models.TextField()
    file = models.CharField(max_length=255, blank=True)
    function = models.CharField(max_length=255, blank=True)
    line = models.PositiveIntegerField(default=0)

    class Meta:
        ordering = ["-id"]
        indexes = [
            models.Index(fields=["robot", "-id"], name="log_robot_recent"),
            models.Index(fields=["node", "-id"], name="log_node_recent"),
            models.Index(fields=["robot", "logger", "-id"], name="log_logger_recent"),
            models.Index(fields=["stamp"], name="log_stamp"),
        ]
        verbose_name = gettext_lazy("log record")
        verbose_name_plural = gettext_lazy("log records")

    @property
    def level_name(self) -> str:
        return dict(self.LEVELS).get(self.level, str(self.level))

    def as_dict(self) -> dict:
        return {
            "id": self.id,
            "stamp": self.stamp.isoformat(),
            "level": self.level_name,
            "logger": self.logger,
            "message": self.message,
            "file": self.file,
            "function": self.function,
            "line": self.line,
        }


from lifecycle_site.fleet.group_runs import GroupRun  # noqa: E402, F401 - registered with this app
from lifecycle_site.fleet.process_profiles import ProcessProfile  # noqa: E402, F401 - registered with this app
