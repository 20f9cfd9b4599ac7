"""Starting, stopping and restarting a robot's process through its supervisor, for the API, the
pages and the CLI alike. The supervisor is the robot's gateway for the processes of the robot's
launch profiles (ros_gateway/supervisor.py), or, for a Docker container or systemd unit the
gateway found running one of the robot's nodes on its host, the Docker Engine or systemd
(ros_gateway/host_units.py; such a process is named "docker:NAME" or "systemd:UNIT").

The gateway acts only on a process of a profile it has for that robot, or on a container or unit
it attributed to one of the robot's nodes itself: a request names the robot and the profile or
that attribution, never a pid. Every attempt is on record: the gateway reports what it did with
its answer (applied here before the answer); what is refused before it reaches the gateway is
recorded here.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from datetime import datetime

from django.utils import timezone
from django.utils.translation import gettext as _
from django.utils.translation import gettext_lazy, pgettext

from lifecycle_site.audit.models import ProcessRecord
from lifecycle_site.fleet.models import ManagedNode, ProcessProfile, Robot
from lifecycle_site.gateway_link.gateway_client import MAX_SERVICE_TIMEOUT, GatewayError, call_gateway
from lifecycle_site.ingest.facts import apply_facts
from lifecycle_site.ingest.live_updates import AUDIT_STORED, push
from lifecycle_site.refusal import Refusal, in_english, shown
from ros_gateway.shared import protocol

# Codes of gateway refusals that mean nothing reached the process (recorded here, then).
NOT_SENT = {"gateway_offline", "robot_not_watched", "unknown_process"}
STATUS_BY_CODE = {"unknown_process": 404, "robot_not_watched": 409}


HOST_PROCESS_RE = protocol.HOST_PROCESS_RE  # a container or unit: "docker:NAME", "systemd:UNIT"
SUPERVISORS = {"launch": gettext_lazy("launch profile"), "docker": gettext_lazy("Docker container"),
               "systemd": gettext_lazy("systemd unit")}
HOST_GRACE_S = 30.0  # a container's or unit's own stop time is its supervisor's; the call waits this much more


class ProcessRefused(Refusal):
    """A process action not carried out (or not as asked); ``details`` has the record's id."""


@dataclass
class HostProcess:
    """A container or systemd unit that the robot's gateway found running some of its nodes, as
    the site knows it: its nodes (``ManagedNode.supervised_by``) and the records of its actions."""

    robot: Robot
    name: str  # "docker:NAME" or "systemd:UNIT"
    nodes: list[str] = field(default_factory=list)
    running: bool = False  # one of its nodes is alive
    pid: int | None = None
    since: datetime | None = None
    restarts: int = 0
    last_exit: dict | None = None
    message: str = ""
    hung: str = ""  # why it looks hung (hung()), if it does
    enabled = True

    @property
    def supervisor(self) -> str:
        return self.name.split(":", 1)[0]

    @property
    def status(self) -> str:
        return ProcessProfile.Status.RUNNING if self.running else ProcessProfile.Status.STOPPED

    def get_status_display(self) -> str:
        return pgettext("process", "running") if self.running else pgettext("process", "not running")

    def as_dict(self) -> dict:
        return {"robot": self.robot.name, "name": self.name, "supervisor": self.supervisor, "nodes": self.nodes,
                "status": self.status, "pid": self.pid, "since": self.since.isoformat() if self.since else None,
                "restarts": self.restarts, "last_exit": self.last_exit, "message": self.message}


STUCK_S = 30.0  # a node in a transition state this long (its callback has not returned) counts as hung


def hung(nodes: list[ManagedNode]) -> str:
    """Why a process looks hung, in words, from its nodes ("" if it does not): one stopped answering
    the gateway's probes (GetState), or is stuck in a transition state."""
    now = timezone.now()
    for node in nodes:
        if not node.alive and node.gone_reason == "unreachable":
            return _("hung: %(node)s stopped answering its gateway's probes (GetState)") % {"node": node.name}
        if node.alive and node.state_id >= 10 and node.state_changed is not None and \
                (stuck := (now - node.state_changed).total_seconds()) >= STUCK_S:
            return _("hung: %(node)s stuck in %(state)s for %(seconds)s s") % {
                "node": node.name, "state": node.state_label, "seconds": f"{stuck:.0f}"}
    return ""


def nodes_by_process(robot: Robot) -> dict[str, list[ManagedNode]]:
    """The robot's nodes by the process (launch profile, container or unit) that runs them."""
    found: dict[str, list[ManagedNode]] = {}
    for node in robot.nodes.exclude(supervised_by="").order_by("name").only(
            "name", "supervised_by", "alive", "gone_reason", "state_id", "state_label", "state_changed"):
        found.setdefault(node.supervised_by, []).append(node)
    return found


def host_processes(robot: Robot, nodes: dict[str, list[ManagedNode]] | None = None) -> list[HostProcess]:
    """The robot's containers and units, from its nodes' ``supervised_by`` and the process records."""
    found: dict[str, HostProcess] = {}
    for name, its_nodes in (nodes_by_process(robot) if nodes is None else nodes).items():
        if HOST_PROCESS_RE.match(name):
            found[name] = HostProcess(robot, name, [n.name for n in its_nodes], any(n.alive for n in its_nodes),
                                      hung=hung(its_nodes))
    for host in found.values():
        records = ProcessRecord.objects.filter(robot_name=robot.name, process_name=host.name).exclude(
            outcome="rejected")
        host.restarts = records.filter(action="restart", outcome="succeeded").count()
        latest = records.first()
        if latest is not None:
            host.message = latest.message
        started = records.filter(action__in=("start", "restart"), outcome="succeeded").first()
        if host.running and started is not None:  # its uptime and pid as of its last start through us
            host.since, host.pid = started.at, started.pid
        ended = records.filter(old_pid__isnull=False).exclude(exit_code=None, exit_signal="").first()
        if ended is not None:
            host.last_exit = {"code": ended.exit_code, "signal": ended.exit_signal or None, "at": ended.at.isoformat()}
    return list(found.values())


def robot_processes(robot: Robot) -> list[ProcessProfile | HostProcess]:
    """Every process the robot has: its launch profiles by name, then its containers and units."""
    return [*robot.process_profiles.order_by("name"), *host_processes(robot)]


USAGE_FRESH_S = 2.0  # one measurement serves every page open on the robot for this long
USAGE_LIMIT, MAX_CPU, MAX_RSS, MAX_COUNT = 512, 100.0 * 1024, 1 << 50, 1_000_000
_usage_seen: dict[str, tuple[float, dict]] = {}  # robot -> (monotonic, its usage)


def usage(robot: Robot, names: set[str]) -> dict[str, dict]:
    """CPU and memory of the robot's processes (``names``), measured by its gateway now (or within
    USAGE_FRESH_S); {} when it cannot tell (offline, no answer within a second). What the gateway
    answers is checked: known names only, bounded numbers."""
    seen = _usage_seen.get(robot.name)
    if seen is not None and time.monotonic() - seen[0] < USAGE_FRESH_S:
        return {name: value for name, value in seen[1].items() if name in names}
    try:
        reply = call_gateway(robot.gateway.name, protocol.PROCESS_USAGE, timeout=1.0, robot=robot.name)
    except GatewayError:
        return {}
    found = reply.get("usage") if isinstance(reply.get("usage"), dict) else {}
    checked = {name: good for name, value in list(found.items())[:USAGE_LIMIT]
               if name in names and (good := _usage_value(value)) is not None}
    if len(_usage_seen) > 1000:
        _usage_seen.clear()
    _usage_seen[robot.name] = (time.monotonic(), checked)
    return checked


def _usage_value(value: object) -> dict | None:
    if not isinstance(value, dict):
        return None
    cpu, rss, count = value.get("cpu_percent"), value.get("rss_bytes"), value.get("processes")
    if cpu is not None and (not isinstance(cpu, (int, float)) or isinstance(cpu, bool) or not 0 <= cpu <= MAX_CPU):
        return None
    if any(not isinstance(v, int) or isinstance(v, bool) or not 0 <= v <= most
           for v, most in ((rss, MAX_RSS), (count, MAX_COUNT))):
        return None
    return {"cpu_percent": cpu, "rss_mb": round(rss / 2**20, 1), "processes": count}


def profile_of(robot: Robot, name: object) -> ProcessProfile | HostProcess:
    """The launch profile, or the container or unit, that ``name`` names on the robot."""
    if isinstance(name, str) and HOST_PROCESS_RE.match(name):
        host = next((h for h in host_processes(robot) if h.name == name), None)
        if host is not None:
            return host
    profile = ProcessProfile.objects.select_related("robot__gateway").filter(robot=robot, name=name).first() \
        if isinstance(name, str) else None
    if profile is None:
        names = [p.name for p in robot_processes(robot)]
        raise ProcessRefused("unknown_process", _(
            "Robot %(robot)s has no process %(process)s (its processes: %(known)s; an admin registers launch "
            "profiles, the gateway finds containers and systemd units running the robot's nodes).") % {
            "robot": robot.name, "process": shown(name),
            "known": ", ".join(names) or pgettext("list of processes", "none known yet")}, 404)
    return profile


def control(profile: ProcessProfile | HostProcess, action: object, user, source: str) -> ProcessRecord:
    """Carry out ``action`` (start, stop, restart) on the profile's process (or the container or
    unit); returns its record, or raises ProcessRefused (the record exists before either)."""
    if action not in protocol.PROCESS_ACTIONS:
        raise ProcessRefused("unknown_action", _("%(action)s is not a process action; use one of %(actions)s.") % {
            "action": shown(action), "actions": ", ".join(protocol.PROCESS_ACTIONS)}, 400)
    robot = profile.robot
    if not robot.enabled or not profile.enabled:  # shown in the asker's language, recorded in English
        record = refused(profile, action, user, source, in_english(disabled, profile))
        raise ProcessRefused("process_disabled", disabled(profile), 409, record_id=record.id)
    gateway = robot.gateway.name
    grace = HOST_GRACE_S if isinstance(profile, HostProcess) else profile.stop_grace_s
    try:
        reply = call_gateway(gateway, protocol.PROCESS_CONTROL, timeout=min(MAX_SERVICE_TIMEOUT, grace + 5.0),
                             robot=robot.name, process=profile.name, action=action, user_id=user.pk, source=source)
    except GatewayError as exc:
        record = _store(gateway, exc.facts)
        if record is None and (exc.code in NOT_SENT or exc.carried_out is False):
            record = refused(profile, action, user, source, exc.english)
        details = {"record_id": record.id} if record is not None else {}
        raise ProcessRefused(exc.code, exc.message, STATUS_BY_CODE.get(exc.code, exc.status),
                             **exc.details, **details) from None
    record = _store(gateway, reply.get("facts") or [])
    if record is None:
        raise ProcessRefused("gateway_error", _("Gateway %(gateway)s answered without a record of what it did to "
                                                "%(process)s; check the robot's processes before you try again.") % {
            "gateway": gateway, "process": profile.name}, 502)
    if record.outcome == "rejected":
        raise ProcessRefused("process_state", record.message, 409, record_id=record.id)
    if record.outcome == "failed":
        raise ProcessRefused("process_failed", record.message, 422, record_id=record.id)
    return record


def disabled(profile: ProcessProfile | HostProcess) -> str:
    """Why no action is sent: the robot, or the launch profile, is disabled."""
    if not profile.robot.enabled:
        return _("Robot %(robot)s is disabled: its gateway runs none of its processes.") % {"robot": profile.robot.name}
    return _("The launch profile %(process)s of %(robot)s is disabled; an admin enables it.") % {
        "process": profile.name, "robot": profile.robot.name}


def _store(gateway: str, facts: list) -> ProcessRecord | None:
    """Apply what the gateway reported with its answer; the (first) process record made."""
    if not facts:
        return None
    applied = apply_facts(gateway, facts)
    push([AUDIT_STORED])
    if applied.created_processes:
        return applied.created_processes[0]
    ids = [str(f.get("id")) for f in facts if isinstance(f, dict) and f.get("type") == protocol.PROCESS]
    return ProcessRecord.objects.filter(fact_id__in=ids).first()  # stored by the ingest process first


def refused(profile: ProcessProfile | HostProcess, action: object, user, source: str, message: str) -> ProcessRecord:
    host = isinstance(profile, HostProcess)
    record = ProcessRecord(profile=None if host else profile, robot_name=profile.robot.name, process_name=profile.name,
                           supervisor=profile.supervisor if host else "launch", action=str(action), outcome="rejected",
                           source=source, requested_by=user, message=message, at=timezone.now())
    record.save()
    push([AUDIT_STORED])
    return record
