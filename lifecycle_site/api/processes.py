"""JSON API for a robot's processes (its launch profiles, run by its gateway, and the Docker
containers and systemd units its gateway found running its nodes): their status, and start,
stop, restart (docs/api.md, "Processes")."""
from __future__ import annotations

from django.http import Http404, HttpRequest, JsonResponse
from django.utils.translation import gettext as _

from lifecycle_site.api.auth import api_view, json_body
from lifecycle_site.audit.models import ProcessRecord
from lifecycle_site.fleet.models import Robot
from lifecycle_site.operations import processes
from lifecycle_site.refusal import Refusal, shown

OPERATE = "fleet.operate_node"
RECORDS_SHOWN = 20


def robot_or_404(name: str) -> Robot:
    robot = Robot.objects.select_related("gateway").filter(name=name).first()
    if robot is None:
        raise Http404(_("There is no robot named %(name)s.") % {"name": shown(name)})
    return robot


@api_view()
def robot_processes(request: HttpRequest, name: str) -> JsonResponse:
    """The robot's launch profiles with what its gateway last reported of each process, then its
    containers and units; with ``?usage=1`` each one's CPU and memory as its gateway measures them
    now (null for one not running, or when the gateway cannot tell)."""
    robot = robot_or_404(name)
    records = ProcessRecord.objects.filter(robot_name=robot.name)[:RECORDS_SHOWN]
    found = [p.as_dict() for p in processes.robot_processes(robot)]
    if request.GET.get("usage") in ("1", "true"):  # CPU and memory, measured by the gateway now
        measured = processes.usage(robot, {p["name"] for p in found})
        found = [{**p, "usage": measured.get(p["name"])} for p in found]
    return JsonResponse({"robot": robot.name, "gateway": robot.gateway.name, "processes": found,
                         "records": [r.as_dict() for r in records]})


@api_view(methods=("POST",), permission=OPERATE)
def process_action(request: HttpRequest, name: str, process: str) -> JsonResponse:
    """``{"action": "start" | "stop" | "restart"}``: carried out by the robot's gateway; the answer
    is the action's audit record (a refusal: the API's error, with the record's id)."""
    body = json_body(request, shape=dict)
    if "action" not in body:
        raise Refusal("missing_field", _('Send {"action": "restart"} (start, stop or restart).'))
    robot = robot_or_404(name)
    record = processes.control(processes.profile_of(robot, process), body["action"], request.user, "api")
    return JsonResponse({"record": record.as_dict(), "process": processes.profile_of(robot, process).as_dict()})
