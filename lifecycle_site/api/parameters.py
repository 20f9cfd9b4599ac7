"""JSON API for a node's parameters: list with descriptors, set (checked), YAML export."""
from __future__ import annotations

from django.http import HttpRequest, HttpResponse, JsonResponse
from django.utils.translation import gettext as _

from lifecycle_site.api.auth import api_view, error, json_body
from lifecycle_site.api.limits import MAX_PARAMETERS
from lifecycle_site.api.views import get_node
from lifecycle_site.fleet.param_files import dump
from lifecycle_site.operations.parameters import apply, fetch


def not_running(node) -> str:
    return _("%(node)s is not running on %(robot)s.") % {"node": node.name, "robot": node.robot.name}


@api_view(methods=("GET", "PATCH"))
def node_parameters(request: HttpRequest, key: str) -> JsonResponse:
    node = get_node(key)
    if not node.alive:
        return error("node_offline", not_running(node), 409)
    if request.method == "GET":
        return JsonResponse({"node": node.key, "parameters": fetch(node)})
    if not request.user.has_perm("fleet.operate_node"):
        return error("forbidden", _("Your role may view parameters but not change them (operator needed)."), 403)
    values = json_body(request)
    if not isinstance(values, dict) or not values:
        return error("missing_field", _('Send the new values as {"name": value, ...}.'), 400)
    if len(values) > MAX_PARAMETERS:  # each one is sent to the node and audited
        return error("too_many_items", _("The body names %(count)s parameters; at most %(most)s are taken in one "
                                         "request (nothing was sent).") % {
            "count": f"{len(values):,}", "most": MAX_PARAMETERS}, 400, limit=MAX_PARAMETERS)
    results = apply(node, values, request.user, "api")
    if all(r["successful"] for r in results):
        return JsonResponse({"node": node.key, "results": results})
    refused = [r["name"] for r in results if not r["successful"]]
    return error(
        "parameters_rejected",
        _("Not set: %(names)s (see results for each reason; the others were set).") % {"names": ", ".join(refused)},
        422,
        results=results,
    )


@api_view()
def parameters_yaml(request: HttpRequest, key: str) -> HttpResponse:
    node = get_node(key)
    if not node.alive:
        return error("node_offline", not_running(node), 409)
    response = HttpResponse(dump(node.name, fetch(node)), content_type="application/x-yaml; charset=utf-8")
    response["Content-Disposition"] = f'attachment; filename="{node.key}.yaml"'
    return response
