"""JSON API for a node's parameters: list with descriptors, set (checked), YAML export."""
from __future__ import annotations

from django.http import HttpRequest, HttpResponse, JsonResponse

from lifecycle_site.api.auth import api_view, error, json_body
from lifecycle_site.api.views import get_node
from lifecycle_site.fleet.gateway_client import call_gateway
from lifecycle_site.fleet.param_files import dump
from ros_gateway.shared import protocol


def fetch(node) -> list[dict]:
    return call_gateway(protocol.GET_PARAMETERS, robot=node.robot.name, node=node.name)["parameters"]


def apply(node, values: dict, user, source: str) -> list[dict]:
    reply = call_gateway(protocol.SET_PARAMETERS, robot=node.robot.name, node=node.name, values=values,
                         user_id=user.pk, source=source)
    return reply["results"]


@api_view(methods=("GET", "PATCH"))
def node_parameters(request: HttpRequest, key: str) -> JsonResponse:
    node = get_node(key)
    if not node.alive:
        return error("node_offline", f"{node.name} is not running on {node.robot.name}.", 409)
    if request.method == "GET":
        return JsonResponse({"node": node.key, "parameters": fetch(node)})
    if not request.user.has_perm("fleet.operate_node"):
        return error("forbidden", "Your role may view parameters but not change them (operator needed).", 403)
    values = json_body(request)
    if isinstance(values, JsonResponse):
        return values
    if not isinstance(values, dict) or not values:
        return error("missing_field", 'Send the new values as {"name": value, ...}.', 400)
    results = apply(node, values, request.user, "api")
    if all(r["successful"] for r in results):
        return JsonResponse({"node": node.key, "results": results})
    refused = [r["name"] for r in results if not r["successful"]]
    return error(
        "parameters_rejected",
        f"Not set: {', '.join(refused)} (see results for each reason; the others were set).",
        422,
        results=results,
    )


@api_view()
def parameters_yaml(request: HttpRequest, key: str) -> HttpResponse:
    node = get_node(key)
    if not node.alive:
        return error("node_offline", f"{node.name} is not running on {node.robot.name}.", 409)
    response = HttpResponse(dump(node.name, fetch(node)), content_type="application/x-yaml; charset=utf-8")
    response["Content-Disposition"] = f'attachment; filename="{node.key}.yaml"'
    return response
