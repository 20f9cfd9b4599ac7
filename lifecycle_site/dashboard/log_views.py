"""Log console pages (per node, per robot) and their text downloads."""
from __future__ import annotations

from datetime import datetime, timedelta

from django.conf import settings
from django.db.models import Q, QuerySet
from django.http import Http404, HttpRequest, HttpResponse, JsonResponse
from django.shortcuts import render
from django.utils import timezone

from lifecycle_site.dashboard import snapshots
from lifecycle_site.dashboard.access import viewer_required
from lifecycle_site.fleet import outages
from lifecycle_site.fleet.models import LogRecord, ManagedNode, Robot

HISTORY_LINES = 500
LEVELS = [name for _, name in LogRecord.LEVELS]
LEVEL_VALUES = {name: value for value, name in LogRecord.LEVELS}
# The console's filters, as the page's address carries them (static/js/logs.js keeps it up to
# date): level at least; text the line must contain / must not contain; node (logger) names to
# keep / to leave out, comma-separated; re=1: the four text fields are regular expressions.
TEXT_FILTERS = ("q", "not", "node", "xnode")
MAX_FILTER_CHARS = 200  # also the longest regular expression the page accepts (logs.js)


def filters_of(request: HttpRequest) -> dict:
    """The filters named in the query string, cut to their bounds."""
    level = request.GET.get("level", "").upper()
    found = {"level": level if level in LEVEL_VALUES else "DEBUG", "re": request.GET.get("re") == "1"}
    for name in TEXT_FILTERS:
        found[name] = request.GET.get(name, "").strip()[:MAX_FILTER_CHARS]
    return found


def _names(text: str) -> list[str]:
    return [name.strip() for name in text.split(",") if name.strip()]


def _target(scope: str, name: str) -> tuple[str, QuerySet, dict]:
    """The title, the records and the page context of a node's or a robot's log."""
    if scope == "node":
        node = ManagedNode.objects.select_related("robot__gateway").filter(key=name).first()
        if node is None:
            raise Http404(f"There is no node {name}.")
        return f"{node.robot.name} {node.name}", LogRecord.objects.filter(node=node), {"node": node}
    robot = Robot.objects.select_related("gateway").filter(name=name).first() if scope == "robot" else None
    if robot is None:
        raise Http404(f"There is no robot {name}.")
    return f"{robot.name} (all nodes)", LogRecord.objects.filter(robot=robot), {"robot": robot}


def _filtered(records: QuerySet, request: HttpRequest) -> QuerySet:
    """The level, and the text filters when they are plain text. Regular expressions are never
    run here: a user's pattern could backtrack for minutes in this shared process. With re=1
    the page applies them, in the user's own browser, to what this returns (logs.js)."""
    found = filters_of(request)
    records = records.filter(level__gte=LEVEL_VALUES[found["level"]])
    if found["re"]:
        return records
    if found["q"]:
        records = records.filter(Q(message__icontains=found["q"]) | Q(logger__icontains=found["q"]))
    if found["not"]:
        records = records.exclude(message__icontains=found["not"]).exclude(logger__icontains=found["not"])
    keep = Q()
    for name in _names(found["node"]):
        keep |= Q(logger__icontains=name)
    records = records.filter(keep)
    for name in _names(found["xnode"]):
        records = records.exclude(logger__icontains=name)
    return records


@viewer_required
def log_console(request: HttpRequest, scope: str, name: str) -> HttpResponse:
    title, records, context = _target(scope, name)
    history = [r.as_dict() for r in reversed(records.order_by("-id")[:HISTORY_LINES])]
    gateway = snapshots.gateway_of(context["node"].robot if "node" in context else context["robot"])
    # The stretches of /rosout not received while the gateway's process was down, from the
    # oldest line shown on (without lines: as far back as log records are kept).
    since = datetime.fromisoformat(history[0]["stamp"]) if history else \
        timezone.now() - timedelta(hours=settings.LIFECYCLE["LOG_KEEP_HOURS"])
    return render(
        request,
        "dashboard/logs.html",
        {
            **context,
            "title": title,
            "scope": scope,
            "name": name,
            "history": history,
            "gaps": outages.recent(gateway["name"], since),
            "levels": LEVELS,
            "gateway": gateway,
            "offline_gateways": [] if gateway["online"] else [gateway],
            "filters": filters_of(request),
            # Loggers are named like the node, dots for slashes: /agv1/lidar logs as agv1.lidar.
            "loggers": [] if "node" in context else sorted(
                n.lstrip("/").replace("/", ".") for n in context["robot"].nodes.values_list("name", flat=True)),
            "max_filter_chars": MAX_FILTER_CHARS,
        },
    )


@viewer_required
def log_download(request: HttpRequest, scope: str, name: str) -> HttpResponse:
    """Everything kept server-side (bounded by the retention settings), oldest first."""
    title, records, _ = _target(scope, name)
    records = _filtered(records, request).order_by("id")
    if request.GET.get("format") == "json":  # for the page, which applies regular expressions itself
        return JsonResponse({"title": title, "records": [r.as_dict() for r in records.iterator(chunk_size=2000)]})
    lines = [f"# /rosout of {title}, downloaded {timezone.now():%Y-%m-%d %H:%M:%S %Z}\n"]
    lines += [
        f"{r.stamp:%Y-%m-%d %H:%M:%S.%f} UTC [{r.level_name}] [{r.logger}] {r.message}\n"
        for r in records.iterator(chunk_size=2000)
    ]
    response = HttpResponse("".join(lines), content_type="text/plain; charset=utf-8")
    safe = name.replace("/", "_")
    response["Content-Disposition"] = f'attachment; filename="{scope}-{safe}-rosout.log"'
    return response


@viewer_required
def log_since(request: HttpRequest, scope: str, name: str) -> JsonResponse:
    """Records after a given id: what a console missed while its WebSocket was down."""
    _, records, _ = _target(scope, name)
    try:
        after = int(request.GET.get("after", 0))
    except ValueError:
        after = 0
    rows = list(records.filter(id__gt=after).order_by("-id")[:HISTORY_LINES])
    return JsonResponse({"records": [r.as_dict() for r in reversed(rows)]})
