"""Fleet overview and node page: first renders; live updates come from consumers.py."""
from __future__ import annotations

import re

from django.contrib import messages
from django.contrib.auth.decorators import permission_required
from django.http import Http404, HttpRequest, HttpResponse
from django.shortcuts import redirect, render
from django.template.loader import render_to_string
from django.utils.translation import gettext as _
from django.views.decorators.http import require_POST

from lifecycle_site.audit import denials
from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.dashboard import attention, runs, snapshots
from lifecycle_site.dashboard.access import viewer_required
from lifecycle_site.dashboard.templatetags.dashboard import dom_id
from lifecycle_site.fleet.models import ManagedNode, Robot
from lifecycle_site.fleet.serializers import node_dict
from lifecycle_site.operations.transitions import TransitionRefused, request_transition
from ros_gateway.shared import state_machine as sm

ROS_NAME = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")
FILTER_STATES = ["attention", "unconfigured", "inactive", "active", "finalized", "busy", "lost", "waiting"]


def _can_operate(request: HttpRequest) -> bool:
    return request.user.has_perm("fleet.operate_node")


def opened(request: HttpRequest) -> list[str]:
    """The collapsed-by-size robots the page has opened (?open=a,b; fleet.js keeps it)."""
    return [name for name in request.GET.get("open", "").split(",") if name][:100]


@viewer_required
def fleet(request: HttpRequest) -> HttpResponse:
    open_robots = opened(request)
    groups = snapshots.fleet(open_robots)
    return render(
        request,
        "dashboard/fleet.html",
        {
            "gateways": groups,
            "robot_names": [robot.name for group in groups for robot, _ in group["robots"]],
            "offline_gateways": snapshots.offline(groups),
            "can_operate": _can_operate(request),
            "filter_states": FILTER_STATES,
            "filters": {k: request.GET.get(k, "") for k in ("robot", "state", "q")},
            "open_param": ",".join(open_robots),
            "attention": attention.view(attention.current([group["gateway"] for group in groups])),
        },
    )


@viewer_required
def robot_section(request: HttpRequest, robot: str) -> HttpResponse:
    """A robot of the fleet page opened (?open=1: all its rows) or collapsed (its counts), for
    the button that toggles it (swapped in for the whole section)."""
    found = snapshots.robot_section(robot, request.GET.get("open") == "1")
    if found is None:
        raise Http404(_("There is no robot %(robot)s.") % {"robot": robot})
    robot_obj, nodes = found
    return render(request, "dashboard/_robot.html",
                  {"robot": robot_obj, "nodes": nodes, "can_operate": _can_operate(request)})


@viewer_required
def fleet_find(request: HttpRequest) -> HttpResponse:
    """Nodes of the page's collapsed robots that the name (and state) filter matches, as links:
    at most snapshots.FIND_MAX, and how many more there are."""
    query = request.GET.get("q", "").strip()[:100]
    state = request.GET.get("state", "")
    names = [name for name in request.GET.get("robots", "").split(",") if name][:100]
    if not names or not (query or state):
        return HttpResponse("")
    keys = set(attention.current()["keys"]) if state == "attention" else None
    found, count = snapshots.find(query, state if state in FILTER_STATES else "", names, keys)
    return render(request, "dashboard/_fleet_matches.html",
                  {"found": found, "count": count, "more": count - len(found), "query": query, "state": state})


def node_or_404(key: str) -> ManagedNode:
    node = ManagedNode.objects.select_related("robot__gateway").filter(key=key).first()
    if node is None:
        raise Http404(_("There is no node %(node)s.") % {"node": key})
    return node


@viewer_required
def node_detail(request: HttpRequest, key: str) -> HttpResponse:
    node = node_or_404(key)
    payload = snapshots.node_with_since(node)
    records = [r.as_dict() for r in TransitionRecord.objects.filter(node=node).select_related("node")[:20]]
    gateway = snapshots.gateway_of(node.robot)
    return render(
        request,
        "dashboard/node.html",
        {
            **snapshots.state_panel(payload, "" if gateway["online"] else gateway["name"], gateway.get("last_beat")),
            "node_obj": node,
            "records": records,
            "last": records[0] if records else None,
            "runs": runs.recent_runs(node.robot_id, node.name).get(node.robot.name, []),
            "gateway": gateway,
            "offline_gateways": [] if gateway["online"] else [gateway],
            "can_operate": _can_operate(request),
        },
    )


@viewer_required
@require_POST
def node_transition(request: HttpRequest, key: str) -> HttpResponse:
    """A transition button: answers with a status message (and the state panel, in case
    the WebSocket is down)."""
    node = node_or_404(key)
    # The node page shows answers in its #transition-result; a fleet row in its own result,
    # naming robot and node (two robots may both have a /camera_driver).
    on_row = request.htmx.target != "transition-result"
    answer = "dashboard/_node_row_result.html" if on_row else "dashboard/_transition_result.html"
    named = {"robot": node.robot.name, "node": node.name, "gateway_name": node.robot.gateway.name}
    if not _can_operate(request):
        denials.record(request, 403, "forbidden", "operator needed")
        outcome_context = {"ok": False, "message": _("Your role may view but not operate nodes (operator needed).")}
        return render(request, answer, {**named, **outcome_context}, status=403)
    try:
        done = request_transition(node, request.POST.get("transition", ""), request.user, "dashboard")
    except TransitionRefused as refused:
        if refused.code == "unknown_transition":  # (no button sends one)
            return render(request, answer, {**named, "ok": False, "message": refused.message}, status=400)
        done, context = None, {"ok": False, "code": refused.code, "message": refused.message}
    else:
        context = {"ok": True, "code": None, "message": done.message}
    if on_row:
        return render(request, answer, {**named, **context})
    node.refresh_from_db()
    payload = snapshots.node_with_since(node)
    if done is not None and done.data.get("to"):  # the gateway's answer is fresher than the database write
        payload = {**payload, "state": done.data["to"],
                   "transitions": [t.as_dict() for t in sm.valid_transitions(done.data["to"]["id"])]}
    context["gateway_name"] = named["gateway_name"]
    if request.htmx.target == "transition-result":  # the node page: refresh its state panel too
        context.update(snapshots.state_panel(payload), can_operate=True, oob=True)
    # htmx swaps only 2xx answers by default; the message is the content either way.
    return render(request, "dashboard/_transition_result.html", context)


@viewer_required
@permission_required("fleet.operate_node", raise_exception=True)
@require_POST
def watch_node(request: HttpRequest, robot: str) -> HttpResponse:
    """Pin a node name to a robot before it exists (it shows as 'waiting' until discovered),
    or, with ``action=unwatch``, drop such a name again. Answered in the page: the message, and
    the row added or removed (a plain form post gets the fleet page again)."""
    robot_obj = Robot.objects.select_related("gateway").filter(name=robot).first()
    if robot_obj is None:
        raise Http404(_("There is no robot %(robot)s.") % {"robot": robot})
    name = request.POST.get("name", "").strip()
    if name and not name.startswith("/"):
        name = "/" + name
    row_html, ok = "", False
    named = {"node": name, "robot": robot}
    if request.POST.get("action") == "unwatch":
        node = ManagedNode.objects.filter(robot=robot_obj, name=name).first()
        if node is None:
            message = _("%(robot)s has no node %(node)s.") % {"robot": robot, "node": name or _("(no name given)")}
        elif node.last_seen is not None:
            message = _("%(node)s on %(robot)s has been seen running, so its history is kept: remove it in the admin "
                        "if it is gone for good.") % named
        else:
            key = node.key
            node.delete()
            ok, message = True, _("No longer watching %(node)s on %(robot)s.") % named
            row_html = f'<tr id="{dom_id(key)}" hx-swap-oob="delete"></tr>'
    elif not ROS_NAME.match(name) or "__" in name or len(name) > ManagedNode._meta.get_field("name").max_length:
        message = (_("%(node)s is not a ROS node name (e.g. /lidar_driver).") % named if name
                   else _("An empty name is not a ROS node name (e.g. /lidar_driver)."))
    else:
        node, created = ManagedNode.objects.get_or_create(robot=robot_obj, name=name)
        ok = True
        if created:
            message = _("Watching %(node)s on %(robot)s: it shows as waiting until it appears.") % named
            row = snapshots.fleet_row(node_dict(node))
            snapshots.mark_gateway([row], snapshots.gateway_of(robot_obj))
            row_html = render_to_string("dashboard/_node_row_new.html",
                                        {"node": row, "nodes": [row], "can_operate": True}, request=request)
        else:
            message = _("%(node)s on %(robot)s is already listed.") % named
    if not request.htmx:
        (messages.success if ok else messages.error)(request, message)
        return redirect("dashboard:fleet")
    answer = render_to_string("dashboard/_node_row_result.html", {"ok": ok, "message": message}, request=request)
    # Table parts after other content are dropped by the HTML parser, unless in a template
    # (htmx swaps out-of-band elements found in one).
    return HttpResponse(answer + (f"<template>{row_html}</template>" if row_html else ""))
