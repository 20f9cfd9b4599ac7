"""Group operations, restart and desired state from the pages (the API has the same in JSON)."""
from __future__ import annotations

from django.db import transaction
from django.http import Http404, HttpRequest, HttpResponse
from django.shortcuts import render
from django.utils.translation import gettext as _
from django.views.decorators.http import require_POST

from lifecycle_site.dashboard import snapshots
from lifecycle_site.dashboard.access import operator_required
from lifecycle_site.dashboard.views import node_or_404
from lifecycle_site.fleet.models import GroupRun, Robot
from lifecycle_site.fleet.serializers import node_dict
from lifecycle_site.operations.desired_state import resume_keeping, set_desired_state, set_keep
from lifecycle_site.operations.runs import start_run
from lifecycle_site.refusal import Refusal


def _run_panel(request: HttpRequest, run: GroupRun | None, runs_in: str, error: str = "",
               status: int = 200, refused: Refusal | None = None, robot: Robot | None = None) -> HttpResponse:
    """The answer to a run's button: an error in place, or the run's panel put into the page's
    run list (out of band: a live update of the same run may have put it there already). A
    refusal because the gateway is offline names it: the page drops it once the gateway is back."""
    context = {"run": run.as_dict() if run else None, "error": error, "runs_in": runs_in}
    if refused is not None and refused.code == "gateway_offline" and robot is not None:
        context["offline_gateway"] = robot.gateway.name
    return render(request, "dashboard/_run.html", context, status=status)


@operator_required
@require_POST
def robot_operation(request: HttpRequest, robot: str) -> HttpResponse:
    robot_obj = Robot.objects.filter(name=robot).first()
    if robot_obj is None:
        raise Http404(_("There is no robot %(robot)s.") % {"robot": robot})
    runs_in = f"robot-{robot_obj.name}-run"
    try:
        timeout = float(request.POST.get("timeout") or 5)
        run = start_run(robot_obj, request.POST.get("operation", ""), user=request.user, source="dashboard",
                        policy=request.POST.get("policy", "stop"), node_timeout=max(0.5, min(timeout, 25.0)))
    except ValueError:
        return _run_panel(request, None, runs_in, _("The timeout must be a number of seconds."))
    except Refusal as exc:
        return _run_panel(request, None, runs_in, exc.message, refused=exc, robot=robot_obj)
    return _run_panel(request, run, runs_in)


@operator_required
@require_POST
def node_restart(request: HttpRequest, key: str) -> HttpResponse:
    node = node_or_404(key)
    refusal = snapshots.restart_refusal(node_dict(node))
    if refusal:
        return _run_panel(request, None, "node-run", refusal)
    try:
        run = start_run(node.robot, "restart", user=request.user, source="dashboard", nodes=[node.name])
    except Refusal as exc:
        return _run_panel(request, None, "node-run", exc.message, refused=exc, robot=node.robot)
    return _run_panel(request, run, "node-run")


@operator_required
@require_POST
def desired_state(request: HttpRequest, key: str) -> HttpResponse:
    node = node_or_404(key)
    try:
        with transaction.atomic():
            if "desired_state" in request.POST:
                set_desired_state(node, request.POST["desired_state"])
            if "keep_desired" in request.POST:
                set_keep(node, request.POST["keep_desired"])
            if "resume" in request.POST:
                resume_keeping(node, request.user)
    except Refusal as refused:
        node.refresh_from_db()  # (rolled back)
        context = {"node_obj": node, "can_operate": True, "error": refused.message}
        return render(request, "dashboard/_desired_state.html", context, status=refused.status)
    return render(request, "dashboard/_desired_state.html", {"node_obj": node, "can_operate": True, "saved": True})
