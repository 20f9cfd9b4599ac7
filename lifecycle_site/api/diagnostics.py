"""GET /api/v1/robots/{name}/diagnostics and .../diagnostics/history (docs/api.md, "Diagnostics"):
a robot's statuses as its nodes report them, as a tree by name path with counts per level, and one
status's level changes, newest first."""
from __future__ import annotations

from django.http import HttpRequest, JsonResponse
from django.utils.translation import gettext as _

from lifecycle_site.api.auth import api_view
from lifecycle_site.api.processes import robot_or_404
from lifecycle_site.diagnostics import history, tree
from lifecycle_site.diagnostics.models import MAX_HISTORY, Intake, Status
from lifecycle_site.refusal import Refusal, shown


@api_view()
def robot_diagnostics(request: HttpRequest, name: str) -> JsonResponse:
    robot = robot_or_404(name)
    statuses = list(Status.objects.filter(robot=robot))
    intake = Intake.objects.filter(robot=robot).first()
    return JsonResponse({
        "robot": robot.name, "counts": tree.counts(statuses),
        "left_out": (intake.left_out_by_gateway + intake.left_out_here) if intake else 0,
        "tree": tree.as_dicts(tree.rows(tree.build(statuses))),
    })


@api_view()
def status_history(request: HttpRequest, name: str) -> JsonResponse:
    robot = robot_or_404(name)
    status_name = request.GET.get("name", "")
    if not status_name:
        raise Refusal("missing_field", _("Name the status: ?name=/Robot/Sensors/Lidar (its full name)."), 400)
    status = Status.objects.filter(robot=robot, name=status_name).first()
    if status is None:
        raise Refusal("not_found", _("Robot %(robot)s has no diagnostic status named %(name)s; "
                                     "GET /api/v1/robots/%(robot)s/diagnostics lists them.") % {
            "robot": robot.name, "name": shown(status_name)}, 404)
    try:
        limit = min(max(int(request.GET.get("limit", MAX_HISTORY)), 1), MAX_HISTORY)
    except ValueError:
        raise Refusal("invalid_field", _("limit must be a whole number from 1 to %(most)s.") % {"most": MAX_HISTORY},
                      400) from None
    return JsonResponse({"robot": robot.name, "status": status.as_dict(),
                         "changes": [c.as_dict() for c in history.changes(robot, status_name, limit)]})
