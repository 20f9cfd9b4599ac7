"""GET /api/v1/nodes/{id}/timeline and /api/v1/robots/{name}/timeline (docs/api.md, "Timeline"):
a node's states over the last 15 minutes, hour, day or week or a range (from, to), time in each,
availability, failures, restarts and the events to look at, rebuilt from the audit log
(lifecycle_site/timelines/node.py)."""
from __future__ import annotations

from django.http import HttpRequest, JsonResponse
from django.utils.translation import gettext as _

from lifecycle_site.api.auth import api_view, error
from lifecycle_site.api.views import get_node
from lifecycle_site.fleet.models import Robot
from lifecycle_site.refusal import Refusal, shown
from lifecycle_site.timelines import node as tl
from lifecycle_site.timelines import windows as tw
from lifecycle_site.timelines.robot import robot_timeline as robot_timeline_of


def _window(request: HttpRequest) -> tw.Window:
    try:
        return tw.parse(request.GET)
    except tw.WindowError as exc:
        if request.GET.get("from") or request.GET.get("to"):
            raise Refusal("invalid_field", f"from, to: {exc}") from None
        asked = request.GET.get("window", "")
        raise Refusal("invalid_field", _("window must be one of %(windows)s, not %(asked)s.") % {
            "windows": ", ".join(tl.WINDOWS), "asked": shown(asked)}) from None


@api_view()
def node_timeline(request: HttpRequest, key: str) -> JsonResponse:
    window = _window(request)
    node = get_node(key)
    return JsonResponse(tl.node_timeline(node, window).as_dict())


@api_view()
def robot_timeline(request: HttpRequest, name: str) -> JsonResponse:
    window = _window(request)
    robot = Robot.objects.filter(name=name).first()
    if robot is None:
        return error("not_found", _("There is no robot named %(name)s; GET /api/v1/robots lists them.") % {
            "name": shown(name)}, 404)
    return JsonResponse(robot_timeline_of(robot, window).as_dict())
