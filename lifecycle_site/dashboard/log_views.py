"""Log console pages (per node, per robot) and their text downloads."""
from __future__ import annotations

import re
from datetime import datetime, timedelta
from datetime import timezone as dt_timezone

from django.conf import settings
from django.db.models import Q, QuerySet
from django.http import Http404, HttpRequest, HttpResponse, JsonResponse
from django.shortcuts import render
from django.utils import dateparse, timezone
from django.utils.translation import gettext as _
from django.utils.translation import pgettext_lazy

from lifecycle_site.dashboard import snapshots
from lifecycle_site.dashboard.access import viewer_required
from lifecycle_site.fleet.models import LogRecord, ManagedNode, Robot
from lifecycle_site.ingest import outages

HISTORY_LINES = 500
AROUND_LINES = HISTORY_LINES // 2  # on each side of a moment the page was opened at (?at=, from the timeline)
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


# How each filter is named in a download's first lines (in the reader's language) and its file
# name (what it keeps).
FILTER_WORDS = (("q", pgettext_lazy("log filter", "text"), "with"),
                ("not", pgettext_lazy("log filter", "without the text"), "without"),
                ("node", pgettext_lazy("log filter", "nodes"), "nodes"),
                ("xnode", pgettext_lazy("log filter", "hiding nodes"), "hiding"))
_UNSAFE_IN_FILE_NAME = re.compile(r"[^A-Za-z0-9._-]+")


def download_names(scope: str, name: str, found: dict) -> tuple[str, str]:
    """The download's file name and its line naming the filters applied, so a file saved
    from a filtered console does not pass for the whole log."""
    said, parts = [], []
    if found["level"] != "DEBUG":
        said.append(_("level %(level)s and above") % {"level": found["level"]})
        parts.append(f"{found['level']}-and-above")
    for key, words, short in FILTER_WORDS:
        if found[key]:
            said.append(f'{words} "{found[key]}"')
            parts.append(f"{short}-" + (_UNSAFE_IN_FILE_NAME.sub("-", found[key]).strip("-")[:40] or "x"))
    if found["re"] and any(found[key] for key, _words, _short in FILTER_WORDS):
        said.append(_("as regular expressions, applied in the browser"))
        parts.append("regex")
    line = _("# filters: %(filters)s") % {"filters": "; ".join(said) if said else _("none (every record kept)")}
    return f"{scope}-{name.replace('/', '_')}-rosout{''.join('_' + p for p in parts)}.log", line


def _names(text: str) -> list[str]:
    return [name.strip() for name in text.split(",") if name.strip()]


def _target(scope: str, name: str) -> tuple[str, QuerySet, dict]:
    """The title, the records and the page context of a node's or a robot's log."""
    if scope == "node":
        node = ManagedNode.objects.select_related("robot__gateway").filter(key=name).first()
        if node is None:
            raise Http404(_("There is no node %(node)s.") % {"node": name})
        return f"{node.robot.name} {node.name}", LogRecord.objects.filter(node=node), {"node": node}
    robot = Robot.objects.select_related("gateway").filter(name=name).first() if scope == "robot" else None
    if robot is None:
        raise Http404(_("There is no robot %(robot)s.") % {"robot": name})
    return _("%(robot)s (all nodes)") % {"robot": robot.name}, LogRecord.objects.filter(robot=robot), {"robot": robot}


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


def _moment(request: HttpRequest) -> datetime | None:
    """The moment the page is asked to show (?at=, ISO 8601, UTC without an offset), if any."""
    try:
        found = dateparse.parse_datetime(request.GET.get("at", "")[:40].strip())
    except ValueError:
        return None
    if found is None:
        return None
    return found.replace(tzinfo=dt_timezone.utc) if found.tzinfo is None else found


def _around(records: QuerySet, at: datetime) -> list:
    """Up to AROUND_LINES lines on each side of ``at`` (by their stamps), in the order they
    came (the console's order)."""
    before = list(records.filter(stamp__lte=at).order_by("-stamp", "-id")[:AROUND_LINES])
    after = list(records.filter(stamp__gt=at).order_by("stamp", "id")[:AROUND_LINES])
    return sorted(before + after, key=lambda r: r.id)


@viewer_required
def log_console(request: HttpRequest, scope: str, name: str) -> HttpResponse:
    title, records, context = _target(scope, name)
    at = _moment(request)
    found = _around(records, at) if at is not None else reversed(records.order_by("-id")[:HISTORY_LINES])
    history = [r.as_dict() for r in found]
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
            "at": at.astimezone(dt_timezone.utc).strftime("%Y-%m-%d %H:%M:%S") if at else "",
            "at_iso": at.isoformat() if at else "",
        },
    )


@viewer_required
def log_download(request: HttpRequest, scope: str, name: str) -> HttpResponse:
    """Everything kept server-side (bounded by the retention settings), oldest first."""
    title, records, _context = _target(scope, name)
    records = _filtered(records, request).order_by("id")
    file_name, filters_line = download_names(scope, name, filters_of(request))
    if request.GET.get("format") == "json":  # for the page, which applies regular expressions itself
        return JsonResponse({"title": title, "file_name": file_name, "filters": filters_line,
                             "records": [r.as_dict() for r in records.iterator(chunk_size=2000)]})
    downloaded = f"{timezone.now():%Y-%m-%d %H:%M:%S %Z}"
    lines = [_("# /rosout of %(title)s, downloaded %(time)s") % {"title": title, "time": downloaded} + "\n",
             filters_line + "\n"]
    lines += [
        f"{r.stamp:%Y-%m-%d %H:%M:%S.%f} UTC [{r.level_name}] [{r.logger}] {r.message}\n"
        for r in records.iterator(chunk_size=2000)
    ]
    response = HttpResponse("".join(lines), content_type="text/plain; charset=utf-8")
    response["Content-Disposition"] = f'attachment; filename="{file_name}"'
    return response


@viewer_required
def log_since(request: HttpRequest, scope: str, name: str) -> JsonResponse:
    """Records after a given id: what a console missed while its WebSocket was down."""
    _title, records, _context = _target(scope, name)
    try:
        after = int(request.GET.get("after", 0))
    except ValueError:
        after = 0
    rows = list(records.filter(id__gt=after).order_by("-id")[:HISTORY_LINES])
    return JsonResponse({"records": [r.as_dict() for r in reversed(rows)]})
