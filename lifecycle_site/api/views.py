"""JSON API v1 (docs/api.md). Reads come from the database (and gateways' heartbeats); lifecycle
calls go through each robot's gateway and every transition attempt lands in the audit log."""
from __future__ import annotations

from django.core.cache import cache
from django.db.models import Count, Q
from django.http import Http404, HttpRequest, JsonResponse
from django.utils.translation import gettext as _
from django.utils.translation import gettext_noop

from lifecycle_site.api.auth import api_view, error, json_body
from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import Gateway, LogRecord, ManagedNode, Robot
from lifecycle_site.fleet.serializers import node_dict
from lifecycle_site.gateway_link import gateway_input as checks
from lifecycle_site.gateway_link import gateways as gateway_status
from lifecycle_site.gateway_link.gateway_client import MAX_SERVICE_TIMEOUT, GatewayError, call_gateway
from lifecycle_site.operations.transitions import request_transition
from lifecycle_site.refusal import both, shown
from ros_gateway.shared import param_types, protocol
from ros_gateway.shared import state_machine as sm

MAX_LIMIT = 1000
LEVELS = {name: value for value, name in LogRecord.LEVELS}


def _limit(request: HttpRequest, default: int) -> int:
    try:
        return max(1, min(int(request.GET.get("limit", default)), MAX_LIMIT))
    except ValueError:
        return default


@api_view()
def robots(request: HttpRequest) -> JsonResponse:
    rows = list(
        Robot.objects.select_related("gateway").annotate(
            node_count=Count("nodes"), alive_count=Count("nodes", filter=Q(nodes__alive=True))
        )
    )
    used = list({r.gateway_id: r.gateway for r in rows}.values())
    online = {s.name: s.online for s in gateway_status.statuses(used)}
    return JsonResponse(
        {
            # Every gateway that has robots is online (true without robots).
            "gateway_online": all(online.values()),
            "robots": [
                {
                    "name": r.name,
                    "domain_id": r.domain_id,
                    "namespace": r.namespace,
                    "description": r.description,
                    "enabled": r.enabled,
                    "gateway": r.gateway.name,
                    "gateway_online": online[r.gateway.name],
                    "online": online[r.gateway.name] and r.enabled and r.alive_count > 0,
                    "node_count": r.node_count,
                    "alive_node_count": r.alive_count,
                }
                for r in rows
            ],
        }
    )


@api_view()
def gateways(request: HttpRequest) -> JsonResponse:
    rows = list(Gateway.objects.prefetch_related("robots"))
    states = gateway_status.statuses(rows)
    return JsonResponse(
        {
            "gateways": [
                gateway_status.describe(row, state, sorted(r.name for r in row.robots.all()))
                for row, state in zip(rows, states, strict=True)
            ]
        }
    )


@api_view()
def nodes(request: HttpRequest) -> JsonResponse:
    queryset = ManagedNode.objects.select_related("robot")
    robot = request.GET.get("robot")
    if robot:
        if not Robot.objects.filter(name=robot).exists():
            return error("not_found", _("There is no robot named %(name)s.") % {"name": shown(robot)}, 404)
        queryset = queryset.filter(robot__name=robot)
    return JsonResponse({"nodes": [node_dict(n) for n in queryset]})


@api_view()
def node_detail(request: HttpRequest, key: str) -> JsonResponse:
    node = get_node(key)
    body = node_dict(node)
    body["available_states"] = [sm.state_dict(s) for s in sm.STATE_LABELS]
    body["transition_graph"] = sm.transition_graph()
    body["described_by"] = "state machine"
    if node.alive:
        try:  # the node's own answer, when it can give one
            body["available_states"], body["transition_graph"] = _described_by_node(node)
            body["described_by"] = "node"
        except GatewayError as exc:
            body["described_by_error"] = exc.message
    return JsonResponse(body)


# A node's states and transition graph are fixed in its code: asked once a minute, not on every
# read (two gateway round trips, the slowest part of this answer under load).
DESCRIPTION_TTL_S = 60.0


def _described_by_node(node: ManagedNode) -> tuple[list, list]:
    key = f"api:described:{node.key}"
    described = cache.get(key)
    if described is None:
        gateway, where = node.robot.gateway.name, {"robot": node.robot.name, "node": node.name}
        try:
            states = checks.small_list(call_gateway(gateway, protocol.GET_AVAILABLE_STATES, **where).get("states"),
                                       "states")
            graph = checks.small_list(call_gateway(gateway, protocol.GET_TRANSITION_GRAPH, **where).get("graph"),
                                      "graph")
        except checks.GatewayInputRefused as exc:  # (its reason in English, as logged and counted)
            text, english = both(gettext_noop("Gateway %(gateway)s answered with something the site cannot read "
                                              "(%(reason)s)."), gateway=gateway, reason=exc)
            raise GatewayError("gateway_error", text, carried_out=False, english=english) from None
        described = (states, graph)
        cache.set(key, described, DESCRIPTION_TTL_S)
    return described


def get_node(key: str) -> ManagedNode:
    node = ManagedNode.objects.select_related("robot__gateway").filter(key=key).first()
    if node is None:
        raise Http404(_("There is no node with id %(id)s; GET /api/v1/nodes lists them.") % {"id": shown(key)})
    return node


@api_view(methods=("POST",), permission="fleet.operate_node")
def transition(request: HttpRequest, key: str) -> JsonResponse:
    body = json_body(request)
    if not isinstance(body, dict) or "transition" not in body:
        return error("missing_field", _('Send {"transition": "configure"} (a label or a numeric id).'), 400)
    timeout = body.get("timeout")
    if timeout is not None and (not param_types.is_number(timeout) or not 0 < timeout <= MAX_SERVICE_TIMEOUT):
        return error("invalid_field", _("'timeout' must be a positive number of seconds, at most %(most)s.") % {
            "most": f"{MAX_SERVICE_TIMEOUT:g}"}, 400)
    done = request_transition(get_node(key), body["transition"], request.user, "api", timeout)
    return JsonResponse(done.data)  # a refusal is answered by api_view


@api_view()
def node_logs(request: HttpRequest, key: str) -> JsonResponse:
    node = get_node(key)
    records = LogRecord.objects.filter(node=node)
    level = request.GET.get("level")
    if level:
        if level.upper() not in LEVELS:
            return error("invalid_field", _("level must be one of %(levels)s.") % {"levels": ", ".join(LEVELS)}, 400)
        records = records.filter(level__gte=LEVELS[level.upper()])
    rows = list(records.order_by("-id")[: _limit(request, 100)])
    return JsonResponse({"node": node.key, "records": [r.as_dict() for r in reversed(rows)]})


@api_view()
def transitions(request: HttpRequest) -> JsonResponse:
    records = TransitionRecord.objects.select_related("node")
    robot = request.GET.get("robot")
    if robot:
        if not Robot.objects.filter(name=robot).exists() and not records.filter(robot_name=robot).exists():
            return error("not_found", _("There is no robot named %(name)s.") % {"name": shown(robot)}, 404)
        records = records.filter(robot_name=robot)
    if request.GET.get("node"):
        wanted = request.GET["node"]
        # Either the node id (agv-1.joy_to_vel) or its ROS name (/joy_to_vel).
        records = records.filter(Q(node__key=wanted) | Q(node_name=wanted))
    return JsonResponse({"transitions": [r.as_dict() for r in records[: _limit(request, 100)]]})
