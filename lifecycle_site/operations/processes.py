"""Starting, stopping and restarting a robot's process through its supervisor (the robot's
gateway, which runs the processes of the robot's launch profiles: ros_gateway/supervisor.py),
for the API, the pages and the CLI alike.

The gateway acts only on a process of a profile it has for that robot: a request names the
robot and the profile, never a pid. Every attempt is on record: the gateway reports what it did
with its answer (applied here before the answer); what is refused before it reaches the
gateway is recorded here.
"""
from __future__ import annotations

from django.utils import timezone

from lifecycle_site.audit.models import ProcessRecord
from lifecycle_site.fleet.facts import apply_facts
from lifecycle_site.fleet.gateway_client import MAX_SERVICE_TIMEOUT, GatewayError, call_gateway
from lifecycle_site.fleet.live_updates import AUDIT_STORED, push
from lifecycle_site.fleet.models import ProcessProfile, Robot
from lifecycle_site.refusal import Refusal, shown
from ros_gateway.shared import protocol

# Codes of gateway refusals that mean nothing reached the process (recorded here, then).
NOT_SENT = {"gateway_offline", "robot_not_watched", "unknown_process"}
STATUS_BY_CODE = {"unknown_process": 404, "robot_not_watched": 409}


class ProcessRefused(Refusal):
    """A process action not carried out (or not as asked); ``details`` has the record's id."""


def profile_of(robot: Robot, name: object) -> ProcessProfile:
    profile = ProcessProfile.objects.select_related("robot__gateway").filter(robot=robot, name=name).first() \
        if isinstance(name, str) else None
    if profile is None:
        names = ", ".join(robot.process_profiles.order_by("name").values_list("name", flat=True)) or "none yet"
        raise ProcessRefused("unknown_process", f"Robot {robot.name} has no process {shown(name)} (its launch "
                             f"profiles: {names}; an admin registers them).", 404)
    return profile


def control(profile: ProcessProfile, action: object, user, source: str) -> ProcessRecord:
    """Carry out ``action`` (start, stop, restart) on the profile's process; returns its record,
    or raises ProcessRefused (the record exists before either)."""
    if action not in protocol.PROCESS_ACTIONS:
        raise ProcessRefused("unknown_action", f"{shown(action)} is not a process action; use one of "
                             f"{', '.join(protocol.PROCESS_ACTIONS)}.", 400)
    robot = profile.robot
    if not robot.enabled or not profile.enabled:
        why = (f"Robot {robot.name} is disabled: its gateway runs none of its processes." if not robot.enabled else
               f"The launch profile {profile.name} of {robot.name} is disabled; an admin enables it.")
        raise ProcessRefused("process_disabled", why, 409, record_id=refused(profile, action, user, source, why).id)
    gateway = robot.gateway.name
    try:
        reply = call_gateway(gateway, protocol.PROCESS_CONTROL, timeout=min(MAX_SERVICE_TIMEOUT,
                                                                              profile.stop_grace_s + 5.0),
                             robot=robot.name, process=profile.name, action=action, user_id=user.pk, source=source)
    except GatewayError as exc:
        record = _store(gateway, exc.facts)
        if record is None and (exc.code in NOT_SENT or exc.carried_out is False):
            record = refused(profile, action, user, source, exc.message)
        details = {"record_id": record.id} if record is not None else {}
        raise ProcessRefused(exc.code, exc.message, STATUS_BY_CODE.get(exc.code, exc.status),
                             **exc.details, **details) from None
    record = _store(gateway, reply.get("facts") or [])
    if record is None:
        raise ProcessRefused("gateway_error", f"Gateway {gateway} answered without a record of what it did to "
                             f"{profile.name}; check the robot's processes before you try again.", 502)
    if record.outcome == "rejected":
        raise ProcessRefused("process_state", record.message, 409, record_id=record.id)
    if record.outcome == "failed":
        raise ProcessRefused("process_failed", record.message, 422, record_id=record.id)
    return record


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


def refused(profile: ProcessProfile, action: object, user, source: str, message: str) -> ProcessRecord:
    record = ProcessRecord(profile=profile, robot_name=profile.robot.name, process_name=profile.name,
                           action=str(action), outcome="rejected", source=source, requested_by=user, message=message,
                           at=timezone.now())
    record.save()
    push([AUDIT_STORED])
    return record
