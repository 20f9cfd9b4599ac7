"""What each rule sees now: the nodes or gateways for which its condition holds, and since when.

The database is the source of truth (what the ingest process stored: a node's state, whether
it is alive, its desired state) plus each gateway's heartbeat. States a node passes through in
milliseconds (errorprocessing) are caught from the facts themselves: ``from_facts``.
"""
from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

from django.db.models import F, Q
from django.utils.translation import gettext as _

from lifecycle_site.alerts.models import Rule
from lifecycle_site.diagnostics.models import LEVEL_WORDS
from lifecycle_site.diagnostics.models import Status as DiagnosticStatus
from lifecycle_site.fleet.models import Gateway, ManagedNode, ProcessProfile
from lifecycle_site.gateway_link import gateways
from lifecycle_site.ingest.observations import GONE, Observation
from lifecycle_site.modes import readiness
from lifecycle_site.modes.models import CurrentMode
from ros_gateway.shared import protocol


@dataclass(frozen=True)
class Condition:
    """A rule's condition holding for one subject (a node's key or a gateway's name)."""

    subject: str
    since: datetime
    summary: str
    gateway: str = ""
    robot: str = ""
    node: str = ""


KEPT = ("alert", "enforce")  # the node policies (keep_desired) under which drift is alerted
MODE_ROBOTS = 500  # robots whose readiness one evaluation works out
DIAGNOSTIC_SUBJECTS = 1000  # statuses one diagnostic rule's evaluation looks at


# Summaries are stored with the alert and sent as they are: written in the site's language
# (LIFECYCLE_LANGUAGE, engine.Engine.evaluate), like its e-mails and webhooks.


def _gone_text(node: str, robot: str, reason: str) -> str:
    if reason == "unreachable":
        return _("Node %(node)s on robot %(robot)s stopped answering the gateway's probes: its process may hang, "
                 "or its host or network link may be down.") % {"node": node, "robot": robot}
    return _("Node %(node)s on robot %(robot)s left the ROS graph: its process ended or was stopped.") % {
        "node": node, "robot": robot}


def node_conditions(rule: Rule, now: datetime) -> dict[str, Condition]:
    nodes = ManagedNode.objects.filter(robot__enabled=True)
    if rule.robot_id:
        nodes = nodes.filter(robot_id=rule.robot_id)
    if rule.gateway_id:
        nodes = nodes.filter(robot__gateway_id=rule.gateway_id)
    if rule.kind == Rule.Kind.STATE:
        nodes = nodes.filter(alive=True, state_label=rule.state)
    elif rule.kind == Rule.Kind.GONE:
        nodes = nodes.filter(alive=False, first_seen__isnull=False)  # seen once, gone now
    elif rule.kind == Rule.Kind.NOT_KEPT:
        # Nodes whose desired state is kept (their own policy, or their robot's), moved away from
        # it while running; or left alone by their gateway after a fight with another manager.
        kept = Q(keep_desired__in=KEPT) | Q(keep_desired="", robot__keep_desired__in=KEPT)
        nodes = nodes.exclude(desired_state="").filter(kept).filter(
            Q(alive=True) & ~Q(state_label=F("desired_state")) | Q(enforcement_stopped__isnull=False))
    else:
        # A node that crashed (or stopped answering) is not in its desired state either: its
        # alert keeps firing rather than resolving at the moment the node was lost.
        nodes = nodes.exclude(desired_state="").filter(
            Q(alive=False, first_seen__isnull=False) | Q(alive=True) & ~Q(state_label=F("desired_state")))
    found = {}
    for row in nodes.values("key", "name", "robot__name", "robot__gateway__name", "state_label", "desired_state",
                            "state_changed", "last_seen", "gone_reason", "alive", "enforcement_stopped",
                            "enforcement_note"):
        if not rule.matches_node(row["name"]):
            continue
        node, robot = row["name"], row["robot__name"]
        if rule.kind == Rule.Kind.STATE:
            since, summary = row["state_changed"], _("Node %(node)s on robot %(robot)s is %(state)s.") % {
                "node": node, "robot": robot, "state": rule.state}
        elif rule.kind == Rule.Kind.GONE:
            since, summary = row["last_seen"], _gone_text(node, robot, row["gone_reason"])
        elif row["enforcement_stopped"] and rule.kind == Rule.Kind.NOT_KEPT:
            since, summary = row["enforcement_stopped"], _("Node %(node)s on robot %(robot)s: %(note)s.") % {
                "node": node, "robot": robot, "note": row["enforcement_note"]}
        elif rule.kind == Rule.Kind.NOT_KEPT:
            since = row["state_changed"]
            summary = _("Node %(node)s on robot %(robot)s was moved to %(state)s; its desired state is "
                        "%(desired)s, kept against other tools.") % {
                "node": node, "robot": robot, "state": row["state_label"], "desired": row["desired_state"]}
        elif not row["alive"]:
            since = row["last_seen"]
            values = {"node": node, "robot": robot, "state": row["state_label"], "desired": row["desired_state"]}
            if row["gone_reason"] == "unreachable":
                summary = _("Node %(node)s on robot %(robot)s is not answering, last known %(state)s; its desired "
                            "state is %(desired)s.") % values
            else:
                summary = _("Node %(node)s on robot %(robot)s is not running (lost), last known %(state)s; its "
                            "desired state is %(desired)s.") % values
        else:
            since = row["state_changed"]
            summary = _("Node %(node)s on robot %(robot)s is %(state)s; its desired state is %(desired)s.") % {
                "node": node, "robot": robot, "state": row["state_label"], "desired": row["desired_state"]}
        found[row["key"]] = Condition(row["key"], since or now, summary, row["robot__gateway__name"], robot, node)
    return found


def gateway_conditions(rule: Rule, now: datetime) -> dict[str, Condition]:
    rows = Gateway.objects.all()
    if rule.gateway_id:
        rows = rows.filter(pk=rule.gateway_id)
    if rule.robot_id:
        rows = rows.filter(robots=rule.robot_id)
    rows = list(rows)
    found = {}
    for row, status in zip(rows, gateways.statuses(rows), strict=True):
        if status.online or status.state == gateways.NEVER:  # one that never ran is not alerted
            continue
        # (the reason without "N s ago": a stored message would say it for ever)
        why = status.reason(ago=False)
        values = {"gateway": row.name, "why": why}
        if status.state == gateways.QUARANTINED:
            summary = _("Gateway %(gateway)s is quarantined (%(why)s): its robots cannot be reached or operated.") \
                % values
        else:
            summary = _("Gateway %(gateway)s is offline (%(why)s): its robots cannot be reached or operated.") % values
        found[row.name] = Condition(row.name, status.last_beat or now, summary, row.name)
    return found


def process_conditions(rule: Rule, now: datetime) -> dict[str, Condition]:
    """Launch profiles whose supervisor stopped respawning them (max failures within the window)."""
    rows = ProcessProfile.objects.filter(robot__enabled=True, enabled=True, status=ProcessProfile.Status.GIVEN_UP)
    if rule.robot_id:
        rows = rows.filter(robot_id=rule.robot_id)
    if rule.gateway_id:
        rows = rows.filter(robot__gateway_id=rule.gateway_id)
    found = {}
    for name, robot, gateway, since in rows.values_list("name", "robot__name", "robot__gateway__name",
                                                        "status_since"):
        subject = f"{robot}:{name}"
        summary = _("Process %(process)s of robot %(robot)s kept ending and is no longer started again by its "
                    "gateway; start it from the robot's Processes page once the cause is fixed.") % {
            "process": name, "robot": robot}
        found[subject] = Condition(subject, since or now, summary, gateway, robot)
    return found


def mode_conditions(rule: Rule, now: datetime) -> dict[str, Condition]:
    """Robots not ready in their current mode (a readiness predicate fails), since when."""
    rows = CurrentMode.objects.filter(robot__enabled=True).select_related("robot__gateway", "mode")
    if rule.robot_id:
        rows = rows.filter(robot_id=rule.robot_id)
    if rule.gateway_id:
        rows = rows.filter(robot__gateway_id=rule.gateway_id)
    found = {}
    for now_mode in rows[:MODE_ROBOTS]:
        if not now_mode.mode.ready_when:
            continue
        result = readiness.evaluate(now_mode)
        if result["ready"]:
            continue
        failing = "; ".join(_("%(condition)s (now %(now)s)") % {"condition": c["words"], "now": c["now"]}
                            for c in result["readiness"] if not c["holds"])
        robot = now_mode.robot
        summary = _("Robot %(robot)s is not ready in mode %(mode)s: %(failing)s.") % {
            "robot": robot.name, "mode": now_mode.mode.name, "failing": failing}
        found[robot.name] = Condition(robot.name, now_mode.not_ready_since or now, summary[:2000],
                                      robot.gateway.name, robot.name)
    return found


def diagnostic_conditions(rule: Rule, now: datetime) -> dict[str, Condition]:
    """Statuses at the rule's level (WARN or worse, ERROR, stale) without a break, since when."""
    since_field = {Rule.Level.WARN: "warn_since", Rule.Level.ERROR: "error_since"}.get(rule.level, "stale_since")
    rows = DiagnosticStatus.objects.filter(robot__enabled=True, **{f"{since_field}__isnull": False})
    if rule.robot_id:
        rows = rows.filter(robot_id=rule.robot_id)
    if rule.gateway_id:
        rows = rows.filter(robot__gateway_id=rule.gateway_id)
    if rule.status_pattern and not any(c in rule.status_pattern for c in "*?"):
        prefix = rule.status_pattern.rstrip("/")
        rows = rows.filter(Q(name=rule.status_pattern) | Q(name__startswith=prefix + "/"))
    found = {}
    for name, robot, gateway, level, stale, message, since in rows.order_by(since_field).values_list(
            "name", "robot__name", "robot__gateway__name", "level", "stale", "message", since_field
    )[:DIAGNOSTIC_SUBJECTS]:
        if not rule.matches_status(name):
            continue
        values = {"name": name, "robot": robot, "time": f"{since:%H:%M:%S}" if since else "?",
                  "level": LEVEL_WORDS.get(level, "ERROR"), "message": message}
        if stale and message:
            summary = _("Diagnostic status %(name)s of robot %(robot)s is stale: no update since before %(time)s "
                        "UTC (last message: %(message)s).") % values
        elif stale:
            summary = _("Diagnostic status %(name)s of robot %(robot)s is stale: no update since before %(time)s "
                        "UTC.") % values
        elif message:
            summary = _("Diagnostic status %(name)s of robot %(robot)s is %(level)s (last message: %(message)s).") \
                % values
        else:
            summary = _("Diagnostic status %(name)s of robot %(robot)s is %(level)s.") % values
        subject = f"{robot}:{name}"
        found[subject] = Condition(subject, since or now, summary[:2000], gateway, robot)
    return found


def current(rule: Rule, now: datetime) -> dict[str, Condition]:
    if rule.kind == Rule.Kind.DIAGNOSTIC:
        return diagnostic_conditions(rule, now)
    if rule.kind == Rule.Kind.PROCESS_GIVEN_UP:
        return process_conditions(rule, now)
    if rule.kind == Rule.Kind.MODE_NOT_READY:
        return mode_conditions(rule, now)
    return node_conditions(rule, now) if rule.watches_nodes else gateway_conditions(rule, now)


def from_facts(rule: Rule, observations: list[Observation]) -> dict[str, Condition]:
    """Conditions that held, however briefly, in the facts just stored: only for rules that fire
    at once (a rule with ``for_seconds`` needs the condition to last, which the database shows)."""
    if rule.for_seconds or rule.kind not in (Rule.Kind.STATE, Rule.Kind.GONE):
        return {}
    wanted = rule.state if rule.kind == Rule.Kind.STATE else GONE
    found = {}
    for seen in observations:
        if seen.state != wanted or not rule.matches_node(seen.node):
            continue
        if rule.robot_id and rule.robot.name != seen.robot:
            continue
        if rule.gateway_id and rule.gateway.name != seen.gateway:
            continue
        if wanted == GONE:
            summary = _gone_text(seen.node, seen.robot, seen.reason)
        else:
            summary = _("Node %(node)s on robot %(robot)s entered %(state)s.") % {
                "node": seen.node, "robot": seen.robot, "state": wanted}
        key = protocol.node_key(seen.robot, seen.node)
        found.setdefault(key, Condition(key, seen.at, summary, seen.gateway, seen.robot, seen.node))
    return found
