"""JSON API for group operations, soft restart and desired state (docs/api.md)."""
from __future__ import annotations

import math

from django.db import transaction
from django.http import Http404, HttpRequest, JsonResponse
from django.utils.translation import gettext as _

from lifecycle_site.api.auth import api_view, error, json_body
from lifecycle_site.api.limits import MAX_NODES
from lifecycle_site.api.views import get_node
from lifecycle_site.fleet.models import GroupRun, ManagedNode, Robot
from lifecycle_site.gateway_link.gateway_client import MAX_SERVICE_TIMEOUT
from lifecycle_site.operations.desired_state import resume_keeping, set_desired_state, set_keep
from lifecycle_site.operations.runs import start_run, wait_for
from lifecycle_site.refusal import Refusal, shown
from ros_gateway.shared import operations, param_types

OPERATE = "fleet.operate_node"
NODE_NAME_LENGTH = ManagedNode._meta.get_field("name").max_length


def _body(request: HttpRequest) -> dict:
    return json_body(request, empty=b"{}", shape=dict)


def positive_seconds(value, name: str, default: float) -> float:
    if value is None:
        return default
    if not param_types.is_number(value) or not 0 < value <= MAX_SERVICE_TIMEOUT:
        raise Refusal("invalid_field", _("'%(name)s' must be a positive number of seconds, at most %(most)s "
                                         "(per node).") % {"name": name, "most": f"{MAX_SERVICE_TIMEOUT:g}"})
    return float(value)


def run_answer(request: HttpRequest, run: GroupRun) -> JsonResponse:
    """202 while the run goes on; with ?wait=S, wait (bounded) and answer 200 once it is done."""
    try:
        wait = float(request.GET.get("wait", 0))
    except ValueError:
        wait = 0.0
    if wait > 0 and math.isfinite(wait):
        run = wait_for(run, wait)
    return JsonResponse({"run": run.as_dict()}, status=200 if run.done else 202)


@api_view(methods=("POST",), permission=OPERATE)
def robot_operation(request: HttpRequest, name: str) -> JsonResponse:
    robot = Robot.objects.filter(name=name).first()
    if robot is None:
        raise Http404(_("There is no robot named %(name)s.") % {"name": shown(name)})
    body = _body(request)
    robot_operations = operations.names(operations.ROBOT)
    if "operation" not in body:
        return error("missing_field", _('Send {"operation": "bringup"} (%(operations)s).') % {
            "operations": ", ".join(robot_operations)}, 400)
    operation = body["operation"]
    if not isinstance(operation, str) or operation not in robot_operations:
        return error("unknown_operation", _("%(operation)s is not an operation of a robot; use one of "
                                            "%(operations)s.") % {
            "operation": shown(operation), "operations": ", ".join(robot_operations)}, 400)
    nodes = body.get("nodes") or []
    if not isinstance(nodes, list) or not all(isinstance(n, str) for n in nodes):
        return error("invalid_field", _("'nodes' must be a list of ROS node names."), 400)
    if len(nodes) > MAX_NODES:
        return error("too_many_items", _("'nodes' names %(count)s nodes; at most %(most)s are taken in one "
                                         "operation (leave it out to run every node of the robot).") % {
            "count": f"{len(nodes):,}", "most": MAX_NODES}, 400, limit=MAX_NODES)
    if any(len(n) > NODE_NAME_LENGTH for n in nodes):
        return error("invalid_field", _("A node name is at most %(most)s characters long.") % {
            "most": NODE_NAME_LENGTH}, 400)
    run = start_run(
        robot, operation, user=request.user, source="api", policy=str(body.get("policy", GroupRun.Policy.STOP)),
        node_timeout=positive_seconds(body.get("timeout"), "timeout", 5.0), nodes=nodes,
    )
    return run_answer(request, run)


@api_view(methods=("POST",), permission=OPERATE)
def node_restart(request: HttpRequest, key: str) -> JsonResponse:
    node = get_node(key)
    body = _body(request)
    run = start_run(node.robot, "restart", user=request.user, source="api", nodes=[node.name],
                    node_timeout=positive_seconds(body.get("timeout"), "timeout", 5.0))
    return run_answer(request, run)


@api_view()
def run_detail(request: HttpRequest, run_id: str) -> JsonResponse:
    run = GroupRun.objects.select_related("robot", "requested_by").filter(pk=run_id).first()
    if run is None:
        raise Http404(_("There is no run %(id)s.") % {"id": shown(run_id)})
    return run_answer(request, run)


@api_view()
def robot_runs(request: HttpRequest, name: str) -> JsonResponse:
    if not Robot.objects.filter(name=name).exists():
        raise Http404(_("There is no robot %(name)s.") % {"name": shown(name)})
    runs = GroupRun.objects.select_related("robot", "requested_by").filter(robot__name=name)[:50]
    return JsonResponse({"runs": [r.as_dict() for r in runs]})


@api_view(methods=("PUT",), permission=OPERATE)
def desired_state(request: HttpRequest, key: str) -> JsonResponse:
    node = get_node(key)
    body = _body(request)
    if not {"desired_state", "keep", "resume"} & set(body):
        return error("missing_field", _('Send {"desired_state": "active"} (or null to clear it), {"keep": '
                                        '"enforce"} (off, alert, enforce; null: as its robot) or {"resume": true} '
                                        '(after a fight).'), 400)
    with transaction.atomic():  # all or nothing: a refusal rolls back what came before it
        if "desired_state" in body:
            set_desired_state(node, body["desired_state"])  # null clears it; false, 0, [] are no state
        if "keep" in body:
            set_keep(node, body["keep"])
        if body.get("resume") is True:
            resume_keeping(node, request.user)
    return JsonResponse(keep_json(node))


def keep_json(node: ManagedNode) -> dict:
    return {"id": node.key, "desired_state": node.desired_state or None, "auto_recover": node.robot.auto_recover,
            "keep": node.keep, "keep_own": node.keep_desired or None,
            "enforcement_stopped": node.enforcement_stopped.isoformat() if node.enforcement_stopped else None,
            "enforcement_note": node.enforcement_note}
