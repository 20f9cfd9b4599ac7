"""A robot's modes page: the mode it is in, how it differs from it and whether it is ready (kept
current by its socket: mode_consumer.py), the run that applied it, and its modes with an Apply
button for operators (which asks first). Admins define modes in the admin, or import a file."""
from __future__ import annotations

import hashlib

from django.http import HttpRequest, HttpResponse
from django.shortcuts import render
from django.views.decorators.http import require_POST

from lifecycle_site.dashboard.access import operator_required, viewer_required
from lifecycle_site.dashboard.process_views import robot_or_404
from lifecycle_site.fleet.models import GroupRun, Robot
from lifecycle_site.modes import drift, yaml_files
from lifecycle_site.operations import modes, words
from lifecycle_site.refusal import Refusal


def live_context(robot: Robot) -> dict:
    """What the live part shows (drift, readiness, the run that applied the mode) and its digest."""
    summary = drift.summary(robot)
    run = GroupRun.objects.select_related("robot", "requested_by").filter(pk=summary.get("run")).first() \
        if summary.get("run") else None
    context = {"robot": robot, "summary": summary, "run": run.as_dict() if run else None, "unknown": drift.UNKNOWN}
    context["seen"] = hashlib.blake2b(repr((summary, context["run"])).encode(), digest_size=12).hexdigest()
    return context


@viewer_required
def robot_modes(request: HttpRequest, robot: str) -> HttpResponse:
    robot_obj = robot_or_404(robot)
    listed = [{**m.as_dict(), "confirm": words.question(modes.MODE_RUN, robot_obj.name, m.name)}
              for m in robot_obj.modes.prefetch_related("robots")]
    return render(request, "dashboard/modes.html", {
        **live_context(robot_obj), "modes": listed,
        "confirm_detail": words.question_detail(modes.MODE_RUN),
        "can_operate": request.user.has_perm("fleet.operate_node"),
        "can_define": request.user.is_staff and request.user.has_perm("modes.change_mode")})


@operator_required
@require_POST
def apply(request: HttpRequest, robot: str, mode: str) -> HttpResponse:
    """Apply: the run's start in words, and the live part redrawn (the mode is now current). A
    refusal a button can meet (gateway offline, robot disabled) is answered 200 with its message."""
    robot_obj = robot_or_404(robot)
    try:
        run = modes.apply_mode(robot_obj, modes.mode_of(robot_obj, mode), user=request.user, source="dashboard",
                               policy="continue" if request.POST.get("policy") == "continue" else "stop")
    except Refusal as refused:
        return render(request, "dashboard/_mode_result.html", {"error": refused.message},
                      status=refused.status if refused.status in (403, 404) else 200)
    return render(request, "dashboard/_mode_result.html", {**live_context(robot_obj), "started": run.as_dict()})


@require_POST
@viewer_required
def import_file(request: HttpRequest, robot: str) -> HttpResponse:
    """An admin's YAML file (this product's export, or a system_modes model file): what it becomes,
    then, with "save", stored as the robot's modes. The text comes back in the preview's form."""
    robot_obj = robot_or_404(robot)
    upload = request.FILES.get("file")
    text = upload.read(yaml_files.MAX_BYTES + 1).decode("utf-8", "replace") if upload else request.POST.get("yaml", "")
    try:
        found = modes.import_modes(text, [robot_obj], request.user, save="save" in request.POST)
    except Refusal as refused:
        return render(request, "dashboard/_mode_import.html", {"error": refused.message, "robot": robot_obj},
                      status=refused.status if refused.status == 403 else 200)
    return render(request, "dashboard/_mode_import.html", {**found, "robot": robot_obj, "yaml": text})
