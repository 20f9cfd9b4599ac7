"""A robot's diagnostics page: its statuses as a tree by name path with level, message, how fresh
and the node that reports each (kept current by its socket: diagnostic_consumer.py); and a status's
own page: its key/values and its level history, drawn over a window as the timelines are."""
from __future__ import annotations

import hashlib
import logging
from urllib.parse import urlencode

from django.http import Http404, HttpRequest, HttpResponse
from django.shortcuts import render
from django.urls import reverse
from django.utils.translation import gettext as _
from django.views.decorators.http import require_POST

from lifecycle_site.dashboard.access import operator_required, viewer_required
from lifecycle_site.dashboard.process_views import robot_or_404
from lifecycle_site.dashboard.timeline_views import window_context
from lifecycle_site.diagnostics import history, tree
from lifecycle_site.diagnostics.models import Intake, LevelChange, Status
from lifecycle_site.fleet.models import ManagedNode, Robot
from lifecycle_site.timelines import windows as tw
from ros_gateway.shared import protocol

log = logging.getLogger(__name__)
SYMBOLS = {"OK": "✓", "WARN": "▲", "ERROR": "✕", "STALE": "?"}  # besides the word: told apart without colour


def row_id(path: str) -> str:
    return "diag-" + hashlib.blake2b(path.encode(), digest_size=8).hexdigest()


def status_url(robot: Robot, name: str) -> str:
    return reverse("dashboard:robot-diagnostic", args=[robot.name]) + "?" + urlencode({"name": name})


def node_links(robot: Robot) -> dict[str, str]:
    """Node name -> its page, for the robot's nodes this site knows."""
    return {name: reverse("dashboard:node", args=[key])
            for name, key in ManagedNode.objects.filter(robot=robot).values_list("name", "key")}


def tree_context(robot: Robot) -> dict:
    statuses = list(Status.objects.filter(robot=robot))
    links = node_links(robot)
    rows = []
    for branch in tree.rows(tree.build(statuses)):
        status = branch.status
        rows.append({
            "id": row_id(branch.path), "label": branch.label, "depth": min(branch.depth, 8), "word": branch.word,
            "symbol": SYMBOLS[branch.word], "status": status, "below": branch.below(),
            "own": status.word if status else "",
            "url": status_url(robot, status.name) if status else "",
            "node_url": links.get(status.node, "") if status else "",
        })
    intake = Intake.objects.filter(robot=robot).first()
    return {"robot": robot, "rows": rows, "counts": tree.counts(statuses), "intake": intake,
            "symbols": SYMBOLS, "not_heard": sum(1 for status in statuses if status.stale)}


@viewer_required
def robot_diagnostics(request: HttpRequest, robot: str) -> HttpResponse:
    robot_obj = robot_or_404(robot)
    base = robot_obj.namespace.rstrip("/")
    return render(request, "dashboard/diagnostics.html", {
        **tree_context(robot_obj), "topics": [f"{base}/{t}" for t in protocol.DIAGNOSTIC_TOPICS],
        "can_operate": request.user.has_perm("fleet.operate_node")})


@operator_required
@require_POST
def forget_stale(request: HttpRequest, robot: str) -> HttpResponse:
    """An operator forgets the robot's stale statuses, with their history (a node removed for good
    would otherwise stay stale in the tree and in "needs attention"); one that is heard again comes
    back as new. The tree is redrawn."""
    robot_obj = robot_or_404(robot)
    names = list(Status.objects.filter(robot=robot_obj, stale=True).values_list("name", flat=True))
    Status.objects.filter(robot=robot_obj, name__in=names).delete()
    LevelChange.objects.filter(robot=robot_obj, name__in=names).delete()
    log.info("%s forgot %d stale diagnostic status(es) of %s: %s", request.user.get_username(), len(names),
             robot_obj.name, ", ".join(names[:20]))
    return render(request, "dashboard/_diagnostic_forgotten.html", {**tree_context(robot_obj), "forgotten": names,
                                                                    "can_operate": True})


@viewer_required
def status_detail(request: HttpRequest, robot: str) -> HttpResponse:
    robot_obj = robot_or_404(robot)
    name = request.GET.get("name", "")
    status = Status.objects.filter(robot=robot_obj, name=name).first()
    if status is None:
        raise Http404(_("Robot %(robot)s has no diagnostic status named %(name)s.") % {
            "robot": robot_obj.name, "name": repr(name[:200])})
    window, warning = tw.page_window(request.GET)
    node = ManagedNode.objects.filter(robot=robot_obj, name=status.node).first() if status.node else None
    return render(request, "dashboard/diagnostic_status.html", {
        **window_context(window, warning), "robot": robot_obj, "status": status, "symbols": SYMBOLS, "node": node,
        "segments": history.lane(robot_obj, name, window.start, window.end),
        "changes": history.changes(robot_obj, name),
        "window_links": [(w, tw.LABELS[w], urlencode({"name": name, "window": w})) for w in tw.WINDOWS],
    })
