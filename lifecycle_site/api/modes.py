"""JSON API for robot modes (docs/api.md, "Robot modes"): a robot's modes, its current one and how
it differs from it; applying a mode (operators); defining modes (admins)."""
from __future__ import annotations

from django.db import transaction
from django.http import Http404, HttpRequest, HttpResponse, JsonResponse
from django.utils.translation import gettext as _
from django.views.decorators.csrf import csrf_exempt

from lifecycle_site.api.auth import api_view, error, json_body
from lifecycle_site.api.operations import positive_seconds, run_answer
from lifecycle_site.api.processes import robot_or_404
from lifecycle_site.fleet.models import GroupRun, Robot
from lifecycle_site.modes import definitions, drift, yaml_files
from lifecycle_site.modes.models import MODE_NAME_VALIDATOR, Mode
from lifecycle_site.operations.modes import apply_mode, import_modes, mode_of
from lifecycle_site.refusal import Refusal, shown

OPERATE, DEFINE = "fleet.operate_node", "modes.change_mode"


def _robots_named(names: object) -> list[Robot]:
    """The robots a request names ("robots": [...]), or the Refusal saying which are not."""
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names) or len(names) > 1000:
        raise Refusal("invalid_field", _("'robots' must be a list of robot names."), 400)
    robots = list(Robot.objects.filter(name__in=names))
    unknown = sorted(set(names) - {r.name for r in robots})
    if unknown:
        raise Refusal("not_found", _("There is no robot named %(names)s.") % {"names": ", ".join(unknown[:5])}, 404)
    return robots


@api_view()
def robot_modes(request: HttpRequest, name: str) -> JsonResponse:
    robot = robot_or_404(name)
    return JsonResponse({"robot": robot.name, **drift.summary(robot),
                         "modes": [m.as_dict() for m in robot.modes.prefetch_related("robots")]})


@api_view()
def robot_drift(request: HttpRequest, name: str) -> JsonResponse:
    robot = robot_or_404(name)
    return JsonResponse({"robot": robot.name, **drift.summary(robot)})


@api_view(methods=("POST",), permission=OPERATE)
def apply(request: HttpRequest, name: str, mode: str) -> JsonResponse:
    robot = robot_or_404(name)
    body = json_body(request, empty=b"{}", shape=dict)
    run = apply_mode(robot, mode_of(robot, mode), user=request.user, source="api",
                     policy=str(body.get("policy", GroupRun.Policy.STOP)),
                     node_timeout=positive_seconds(body.get("timeout"), "timeout", 5.0))
    return run_answer(request, run)


@api_view()
def modes(request: HttpRequest) -> JsonResponse:
    return JsonResponse({"modes": [m.as_dict() for m in Mode.objects.prefetch_related("robots")]})


@csrf_exempt  # each method's view checks CSRF for a session (api_view)
def mode(request: HttpRequest, name: str) -> JsonResponse:
    """GET for anyone who may view; PUT (create or replace) and DELETE for admins."""
    return (_mode_read if request.method == "GET" else _mode_write)(request, name)


@api_view()
def _mode_read(request: HttpRequest, name: str) -> JsonResponse:
    found = Mode.objects.filter(name=name).first()
    if found is None:
        raise Http404(_("There is no mode named %(name)s.") % {"name": shown(name)})
    return JsonResponse({"mode": found.as_dict()})


@api_view(methods=("PUT", "DELETE"), permission=DEFINE)
def _mode_write(request: HttpRequest, name: str) -> JsonResponse:
    if request.method == "DELETE":
        deleted, _by_model = Mode.objects.filter(name=name).delete()
        if not deleted:
            raise Http404(_("There is no mode named %(name)s.") % {"name": shown(name)})
        return JsonResponse({"deleted": name})
    try:
        MODE_NAME_VALIDATOR(name)
    except Exception:  # ValidationError: the name is the path's
        return error("invalid_field", f"{shown(name)}: {MODE_NAME_VALIDATOR.message}", 400)  # (the validator's words)
    body = json_body(request, shape=dict, wanted='{"robots": ["agv-1"], "nodes": {"/lidar_driver": '
                                                 '{"state": "active", "parameters": {}}}, "ready_when": []}')
    nodes, robots, description = body.get("nodes", {}), body.get("robots", []), body.get("description", "")
    ready_when = body.get("ready_when", [])
    problems = definitions.problems(nodes) + definitions.readiness_problems(ready_when)
    if problems:
        return error("invalid_mode", " ".join(problems[:5]), 400, problems=problems[:50])
    found = _robots_named(robots)
    if not isinstance(description, str) or len(description) > 2000:
        return error("invalid_field", _("'description' must be a text of at most 2000 characters."), 400)
    with transaction.atomic():
        saved, created = Mode.objects.update_or_create(
            name=name, defaults={"nodes": nodes, "description": description, "ready_when": ready_when,
                                 "updated_by": request.user})
        saved.robots.set(found)
    return JsonResponse({"mode": saved.as_dict()}, status=201 if created else 200)


@api_view()
def robot_modes_yaml(request: HttpRequest, name: str) -> HttpResponse:
    robot = robot_or_404(name)
    body = yaml_files.export([m.as_dict() for m in robot.modes.prefetch_related("robots")])
    response = HttpResponse(body, content_type="application/yaml; charset=utf-8")
    response["Content-Disposition"] = f'attachment; filename="{robot.name}-modes.yaml"'
    return response


@api_view(methods=("POST",), permission=DEFINE)
def import_file(request: HttpRequest) -> JsonResponse:
    """{"yaml": TEXT, "robots": [names], "save": false}: what the file's modes would be (and any
    problem); with "save": true, stored when there is none."""
    body = json_body(request, shape=dict, wanted='{"yaml": "modes: ...", "robots": ["agv-1"], "save": false}')
    text, names = body.get("yaml"), body.get("robots", [])
    if not isinstance(text, str):
        return error("missing_field", _("Send the file's text as 'yaml'."), 400)
    found = import_modes(text, _robots_named(names), request.user, save=body.get("save") is True)
    return JsonResponse(found, status=201 if found["saved"] else 200)
