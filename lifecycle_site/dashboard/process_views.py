"""A robot's processes page: its launch profiles as its gateway (their supervisor) last reported
them, the containers and systemd units its gateway found running its nodes, the latest actions
on them, and start, stop and restart for operators.

The page asks for its rows every few seconds (POLL_SECONDS) rather than holding a socket: an
exit or a respawn reaches the database as the gateway's facts, and the next poll shows it. A
poll sends the digest of what the page shows; unchanged, the answer is an empty 204 (nothing
swapped, the keyboard focus and an open question stay where they are)."""
from __future__ import annotations

import hashlib
import re

from django.http import Http404, HttpRequest, HttpResponse
from django.shortcuts import render
from django.utils.translation import gettext as _
from django.utils.translation import pgettext, pgettext_lazy
from django.views.decorators.http import require_POST

from lifecycle_site.audit.models import ProcessRecord
from lifecycle_site.dashboard import snapshots
from lifecycle_site.dashboard.access import operator_required, polled, refresh_page, viewer_required
from lifecycle_site.fleet.models import ProcessProfile, Robot
from lifecycle_site.operations import processes
from lifecycle_site.refusal import shown

RECORDS_SHOWN = 20
POLL_SECONDS = 3
RUNNING = {ProcessProfile.Status.STARTING, ProcessProfile.Status.RUNNING, ProcessProfile.Status.STOPPING}
# Not running, but waiting to be started again: a stop cancels that.
STOPPABLE = RUNNING | {ProcessProfile.Status.BACKING_OFF}
START, RESTART, STOP = "start", "restart", "stop"
ACTION_LABELS = {START: pgettext_lazy("process button", "Start"), RESTART: pgettext_lazy("process button", "Restart"),
                 STOP: pgettext_lazy("process button", "Stop")}
# The words of a refusal's heading, by its code; others: "Refused".
REFUSAL_HEADINGS = {"gateway_offline": pgettext_lazy("process refusal", "Gateway offline"),
                    "process_state": pgettext_lazy("process refusal", "Not possible"),
                    "process_failed": pgettext_lazy("process refusal", "Failed"),
                    "process_disabled": pgettext_lazy("process refusal", "Disabled"),
                    "timeout": pgettext_lazy("process refusal", "Timed out"),
                    "unknown_process": pgettext_lazy("process refusal", "No such process"),
                    "unknown_action": pgettext_lazy("process refusal", "No such action")}


def _actions(*names: str) -> list[dict]:
    """A row's buttons, labelled in the active language (the digest of the rows takes the words)."""
    return [{"name": name, "label": str(ACTION_LABELS[name])} for name in names]


def robot_or_404(name: str) -> Robot:
    robot = Robot.objects.select_related("gateway").filter(name=name).first()
    if robot is None:
        raise Http404(_("There is no robot %(robot)s.") % {"robot": shown(name)})
    return robot


def _row(profile: ProcessProfile, blocked: str, nodes: list) -> dict:
    """A profile as its row shows it (never its environment: it may hold secrets), with the
    buttons that fit its status and why none can act now (``blocked``), if so."""
    status = profile.status
    actions = _actions(RESTART if status in RUNNING else START, *([STOP] if status in STOPPABLE else []))
    if not blocked and not profile.enabled:
        blocked = _("The launch profile %(profile)s is disabled; an admin enables it.") % {"profile": profile.name}
    return {
        "id": profile.pk, "name": profile.name, "command": profile.command_line(), "enabled": profile.enabled,
        "supervisor": processes.SUPERVISORS["launch"], "nodes": [n.name for n in nodes],
        "hung": processes.hung(nodes) if status in RUNNING else "",
        "status": status, "status_label": profile.get_status_display(), "pid": profile.pid,
        "since": profile.status_since.isoformat() if profile.status_since else None,
        "restarts": profile.restarts,
        "exit_code": profile.last_exit_code, "exit_signal": profile.last_exit_signal,
        "exit_at": profile.last_exit_at.isoformat() if profile.last_exit_at else None,
        "message": profile.last_message, "actions": actions, "blocked": blocked,
    }


def _host_row(host: processes.HostProcess, blocked: str) -> dict:
    """A container's or unit's row: what the site knows of it (its nodes, the actions on record)."""
    exit_ = host.last_exit or {}
    return {
        "id": "unit-" + re.sub(r"[^A-Za-z0-9_-]", "-", host.name), "name": host.name, "command": "", "enabled": True,
        "supervisor": processes.SUPERVISORS[host.supervisor], "nodes": host.nodes, "hung": host.hung,
        "status": host.status,
        "status_label": host.get_status_display(), "pid": host.pid,
        "since": host.since.isoformat() if host.since else None, "restarts": host.restarts,
        "exit_code": exit_.get("code"), "exit_signal": exit_.get("signal"), "exit_at": exit_.get("at"),
        "message": host.message, "actions": _actions(RESTART, STOP) if host.running else _actions(START),
        "blocked": blocked,
    }


def _record(record: ProcessRecord) -> dict:
    return {"id": record.id, "at": record.at.isoformat(), "process": record.process_name,
            "action": record.get_action_display(), "outcome": record.outcome, "source": record.get_source_display(),
            "by": record.requested_by_name, "message": record.message}


def _live(request: HttpRequest, robot: Robot) -> dict:
    """What the polled part of the page shows, and its digest (``seen``)."""
    gateway = snapshots.gateway_of(robot)
    blocked = "" if gateway["online"] else _("The gateway %(gateway)s is offline: no command can be sent.") % {
        "gateway": gateway["name"]}
    if not robot.enabled:
        blocked = _("%(robot)s is disabled: its gateway runs none of its processes.") % {"robot": robot.name}
    nodes = processes.nodes_by_process(robot)
    rows = [_row(p, blocked, nodes.get(p.name, [])) for p in robot.process_profiles.order_by("name")]
    rows += [_host_row(host, blocked) for host in processes.host_processes(robot, nodes)]
    records = [_record(r) for r in ProcessRecord.objects.filter(robot_name=robot.name)[:RECORDS_SHOWN]]
    user = request.user
    context = {
        "robot": robot, "rows": rows, "records": records, "gateway": gateway,
        "can_operate": user.has_perm("fleet.operate_node"),
        "can_register": user.is_staff and user.has_perm("fleet.add_processprofile"),
    }
    # What changes the rendered part; not the clock (the page counts uptimes and ages itself).
    state = (rows, [r["id"] for r in records], gateway["online"], gateway["reason_plain"], gateway["reason_since"],
             robot.enabled, context["can_operate"], context["can_register"])
    context["seen"] = hashlib.blake2b(repr(state).encode(), digest_size=12).hexdigest()
    return context


@viewer_required
def robot_processes(request: HttpRequest, robot: str) -> HttpResponse:
    robot_obj = robot_or_404(robot)
    return render(request, "dashboard/processes.html", {**_live(request, robot_obj), "poll_seconds": POLL_SECONDS})


@polled
def robot_processes_rows(request: HttpRequest, robot: str) -> HttpResponse:
    """The polled part: 204 while it shows what the page has (``?seen=`` its digest)."""
    robot_obj = Robot.objects.select_related("gateway").filter(name=robot).first()
    if robot_obj is None:  # removed since the page was opened
        return refresh_page()
    context = _live(request, robot_obj)
    if request.GET.get("seen") == context["seen"]:
        return HttpResponse(status=204)
    return render(request, "dashboard/_process_live.html", context)


@polled
def robot_processes_usage(request: HttpRequest, robot: str) -> HttpResponse:
    """CPU and memory of each running process, as its gateway measures them now: cells swapped out
    of band (the rows are not redrawn: the keyboard focus and an open question stay). 204 when
    nothing runs or the gateway cannot tell."""
    robot_obj = Robot.objects.select_related("gateway").filter(name=robot).first()
    if robot_obj is None or not robot_obj.enabled or not snapshots.gateway_of(robot_obj)["online"]:
        return HttpResponse(status=204)
    rows = [_row(p, "", []) for p in robot_obj.process_profiles.filter(status__in=RUNNING).order_by("name")]
    rows += [_host_row(h, "") for h in processes.host_processes(robot_obj) if h.running]
    found = processes.usage(robot_obj, {row["name"] for row in rows}) if rows else {}
    cells = [{"id": row["id"], **found[row["name"]]} for row in rows if row["name"] in found]
    if not cells:
        return HttpResponse(status=204)
    return render(request, "dashboard/_process_usage.html", {"cells": cells})


@operator_required
@require_POST
def process_action(request: HttpRequest, robot: str, process: str, action: str) -> HttpResponse:
    """A process's button: the outcome in words, with the page's rows and records out of band
    (the keyboard focus then on the process's row: the button pressed may be gone).

    htmx swaps only 2xx answers, so a refusal a button can meet (the gateway offline, the
    process not in a state for it) is answered 200 with its message, as the project's other
    pages do; what no button sends (an unknown process or action) gets the refusal's status."""
    robot_obj = robot_or_404(robot)
    try:
        profile = processes.profile_of(robot_obj, process)
        record = processes.control(profile, action, request.user, "dashboard")
    except processes.ProcessRefused as refused:
        if refused.code in ("unknown_process", "unknown_action"):
            context = {"ok": False, "heading": REFUSAL_HEADINGS[refused.code], "message": refused.message}
            return render(request, "dashboard/_process_result.html", context, status=refused.status)
        context = {"ok": False, "code": refused.code, "message": refused.message,
                   "heading": REFUSAL_HEADINGS.get(refused.code) or pgettext("process refusal", "Refused")}
    else:
        context = {"ok": True, "message": record.message}
    if request.POST.get("from") == "node":  # the node page's button: only the outcome
        return render(request, "dashboard/_process_result.html", {**context, "robot": robot_obj})
    live = _live(request, robot_obj)
    focus = next((row["id"] for row in live["rows"] if row["name"] == process), None)
    return render(request, "dashboard/_process_result.html",
                  {**context, **live, "focus": focus, "live": True})
