"""A robot's diagnostics page: its statuses as a tree by name path with level, message, how fresh
and the node that reports each (kept current by its socket: diagnostic_consumer.py); and a status's
own page: its key/values and its level history, drawn over a window as the timelines are."""
from __future__ import annotations

import hashlib
from urllib.parse import urlencode

from django.http import Http404, HttpRequest, HttpResponse
from django.shortcuts import render
from django.urls import reverse

from lifecycle_site.dashboard.access import viewer_required
from lifecycle_site.dashboard.process_views import robot_or_404
from lifecycle_site.dashboard.timeline_views import window_context
from lifecycle_site.diagnostics import history, tree
from lifecycle_site.diagnostics.models import Intake, Status
from lifecycle_site.fleet.models import ManagedNode, Robot
from lifecycle_site.timelines import windows as tw
from ros_gateway.shared import protocol

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
            "symbols": SYMBOLS}


@viewer_required
def robot_diagnostics(request: HttpRequest, robot: str) -> HttpResponse:
    robot_obj = robot_or_404(robot)
    base = robot_obj.namespace.rstrip("/")
    return render(request, "dashboard/diagnostics.html", {
        **tree_context(robot_obj), "topics": [f"{base}/{t}" for t in protocol.DIAGNOSTIC_TOPICS]})


@viewer_required
def status_detail(request: HttpRequest, robot: str) -> HttpResponse:
    robot_obj = robot_or_404(robot)
    name = request.GET.get("name", "")
    status = Status.objects.filter(robot=robot_obj, name=name).first()
    if status is None:
        raise Http404(f"Robot {robot_obj.name} has no diagnostic status named {name[:200]!r}.")
    window, warning = tw.page_window(request.GET)
    node = ManagedNode.objects.filter(robot=robot_obj, name=status.node).first() if status.node else None
    return render(request, "dashboard/diagnostic_status.html", {
        **window_context(window, warning), "robot": robot_obj, "status": status, "symbols": SYMBOLS, "node": node,
        "segments": history.lane(robot_obj, name, window.start, window.end),
        "changes": history.changes(robot_obj, name),
        "window_links": [(w, tw.LABELS[w], urlencode({"name": name, "window": w})) for w in tw.WINDOWS],
    })
