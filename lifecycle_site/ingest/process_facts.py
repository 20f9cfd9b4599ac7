"""A gateway's ``process`` facts (ros_gateway/supervisor.py): one audit record each, and the
process's status on its launch profile as the gateway last reported it. Applied by
ingest.facts, in its transaction, like every other fact; checked like all of them (a gateway is
a stranger): a process of one of its own robots' profiles by exact name, known actions,
outcomes and sources, bounded numbers and texts."""
from __future__ import annotations

import re
from datetime import datetime
from typing import Any

from django.db.models import F, Q

from lifecycle_site.audit.models import ProcessRecord
from lifecycle_site.fleet.process_profiles import ProcessProfile
from lifecycle_site.gateway_link import attribution
from lifecycle_site.gateway_link import gateway_input as checks
from lifecycle_site.gateway_link.gateway_input import FactRejected
from lifecycle_site.ingest.fact_context import Applied, KnownRecords, save_once
from ros_gateway.shared import protocol

PROCESS_NAME_RE = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")  # a launch profile's
HOST_PROCESS_RE, SUPERVISORS = protocol.HOST_PROCESS_RE, protocol.SUPERVISORS  # a container or unit (host_units.py)
SIGNAL_RE = re.compile(r"^SIG[A-Z0-9+-]{1,12}$")
MAX_PID = 4_194_304  # Linux's pid_max limit
OUTCOMES = ("succeeded", "failed", "rejected")
Status = ProcessProfile.Status
# The status a succeeded action leaves the process in (a failed start leaves it exited).
AFTER = {"start": Status.RUNNING, "restart": Status.RUNNING, "respawn": Status.RUNNING, "stop": Status.STOPPED,
         "exited": Status.EXITED, "gave_up": Status.GIVEN_UP}


def _pid(value: Any, what: str) -> int | None:
    if value is None:
        return None
    if not isinstance(value, int) or isinstance(value, bool) or not 0 < value <= MAX_PID:
        raise FactRejected(f"{what} must be a process id")
    return value


def _exit_code(value: Any) -> int | None:
    if value is None:
        return None
    if not isinstance(value, int) or isinstance(value, bool) or not -255 <= value <= 255:
        raise FactRejected("exit_code must be an exit status (-255 to 255)")
    return value


def _signal(value: Any) -> str:
    if value in (None, ""):
        return ""
    if not isinstance(value, str) or not SIGNAL_RE.match(value):
        raise FactRejected("exit_signal must name a signal, e.g. SIGKILL")
    return value


def _took(value: Any) -> float | None:
    if value is None:
        return None
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not 0 <= value <= 3_600_000:
        raise FactRejected("took_ms must be a duration in milliseconds")
    return round(float(value), 2)


def process_name(value: Any) -> str:
    if not isinstance(value, str) or not (PROCESS_NAME_RE.match(value) or HOST_PROCESS_RE.match(value)):
        raise FactRejected('process must be a launch profile\'s name, or "docker:NAME" or "systemd:UNIT"')
    return value


def apply_process(known: KnownRecords, fact: dict, at: datetime, applied: Applied) -> None:
    fact_id = str(fact["id"])
    if fact_id in known.stored:
        return
    robot = known.robot(fact)
    name = process_name(fact.get("process"))
    supervisor = checks.choice(fact.get("supervisor") or "launch", SUPERVISORS, "supervisor")
    if not (PROCESS_NAME_RE.match(name) if supervisor == "launch" else name.startswith(f"{supervisor}:")):
        raise FactRejected(f"process {name!r} is not one a {supervisor} supervisor has")
    profile = ProcessProfile.objects.filter(robot=robot, name=name).first() if supervisor == "launch" else None
    action = checks.choice(fact.get("action"), ProcessRecord.Action.values, "action")
    outcome = checks.choice(fact.get("outcome"), OUTCOMES, "outcome")
    source, user_id, claimed = attribution.process_requester(known, fact)
    pid, old_pid = _pid(fact.get("pid"), "pid"), _pid(fact.get("old_pid"), "old_pid")
    exit_code, exit_signal = _exit_code(fact.get("exit_code")), _signal(fact.get("exit_signal"))
    record = ProcessRecord(
        fact_id=fact_id, profile=profile, robot_name=robot.name, process_name=name, supervisor=supervisor,
        action=action, outcome=outcome,
        source=source, pid=pid, old_pid=old_pid, exit_code=exit_code, exit_signal=exit_signal,
        message=checks.text(fact.get("message")) + claimed, took_ms=_took(fact.get("took_ms")), at=at,
        **({} if user_id is None or known.username(user_id) is None else
           {"requested_by_id": user_id, "requested_by_name": known.username(user_id)}),
    )
    if not save_once(known, record):
        return
    applied.created_processes.append(record)
    if profile is not None and outcome != "rejected":
        _follow(profile, action, outcome, record, at)


def _follow(profile: ProcessProfile, action: str, outcome: str, record: ProcessRecord, at: datetime) -> None:
    """The profile's status after the record (a report older than the one shown changes nothing)."""
    changes: dict[str, Any] = {"status_since": at, "last_message": record.message}
    if outcome == "succeeded":
        changes["status"] = AFTER[action]
        changes["pid"] = record.pid if changes["status"] == Status.RUNNING else None
        if action in ("restart", "respawn"):
            changes["restarts"] = F("restarts") + 1
    else:  # a start that failed, giving up
        changes["status"] = Status.GIVEN_UP if action == "gave_up" else Status.EXITED
        changes["pid"] = None
    if action == "exited" or record.exit_code is not None or record.exit_signal:
        changes.update(last_exit_code=record.exit_code, last_exit_signal=record.exit_signal, last_exit_at=at)
    ProcessProfile.objects.filter(pk=profile.pk).filter(Q(status_since__isnull=True) | Q(status_since__lte=at)) \
        .update(**changes)


def apply_node_process(known: KnownRecords, fact: dict, at: datetime, applied: Applied) -> None:
    """Which launch profile's process runs a node (ros_gateway/process_owners.py); "" for none."""
    robot = known.robot(fact)
    node = known.node(robot, checks.node_name(fact.get("node")))
    name = fact.get("process")
    name = "" if name in (None, "") else process_name(name)
    if node is not None:
        type(node).objects.filter(pk=node.pk).update(supervised_by=name)
