"""A gateway's ``diagnostics`` facts (ros_gateway/diagnostics.py), checked and stored: each
status's latest report, its level changes as history, and the pages told which changed.

A gateway is a stranger: the fact must name one of its own robots and that robot's own
diagnostics topics, and everything in it is bounded (statuses per fact and per robot, text,
key/values); what does not fit is refused, or, past the statuses per robot, counted as left out."""
from __future__ import annotations

from datetime import datetime, timedelta
from typing import Any

from django.conf import settings
from django.db import connection
from django.db.models import F

from lifecycle_site.diagnostics.models import ERROR, MAX_HISTORY, STALE, WARN, Intake, LevelChange, Status, page_group
from lifecycle_site.gateway_link import gateway_input as checks
from lifecycle_site.gateway_link.gateway_input import GatewayInputRefused
from lifecycle_site.ingest.fact_context import Applied, KnownRecords
from ros_gateway.shared import param_types as pt
from ros_gateway.shared import protocol

FIELDS = ["level", "stale", "message", "hardware_id", "values", "topic", "node", "heard", "level_since",
          "warn_since", "error_since", "stale_since"]
MAX_AGE_S = 7 * 24 * 3600.0


def _status(item: Any, topics: tuple[str, ...]) -> dict:
    if not isinstance(item, dict):
        raise GatewayInputRefused("a status must be an object")
    name = item.get("name")
    if not isinstance(name, str) or not 0 < len(name) <= protocol.MAX_STATUS_NAME:
        raise GatewayInputRefused(f"a status name must be text of 1 to {protocol.MAX_STATUS_NAME} characters")
    level = item.get("level")
    if not isinstance(level, int) or isinstance(level, bool) or level not in protocol.DIAGNOSTIC_LEVELS:
        raise GatewayInputRefused(f"status {name[:80]!r}: level must be 0, 1, 2 or 3")
    values = item.get("values")
    if not isinstance(values, list) or len(values) > protocol.MAX_STATUS_VALUES or not all(
            isinstance(p, list) and len(p) == 2 and all(isinstance(x, str) for x in p) for p in values):
        raise GatewayInputRefused(f"status {name[:80]!r}: values must be at most {protocol.MAX_STATUS_VALUES} "
                                  "[key, value] pairs of text")
    if item.get("topic") not in topics:
        raise GatewayInputRefused(f"status {name[:80]!r}: not from the robot's diagnostics topics")
    node = item.get("node") or ""
    age = item.get("age_s")
    if not (pt.is_number(age) and 0 <= age <= MAX_AGE_S):
        raise GatewayInputRefused(f"status {name[:80]!r}: age_s must be a number of seconds")
    return {"name": checks.text(name, protocol.MAX_STATUS_NAME), "level": level,
            "stale": item.get("stale") is True,
            "message": checks.text(item.get("message"), protocol.MAX_STATUS_MESSAGE),
            "hardware_id": checks.text(item.get("hardware_id"), protocol.MAX_HARDWARE_ID),
            "values": [[checks.text(k, protocol.MAX_VALUE_KEY), checks.text(v, protocol.MAX_VALUE_TEXT)]
                       for k, v in values],
            "topic": item["topic"], "node": checks.node_name(node) if node else "", "age_s": float(age)}


def _since(status: Status, at: datetime) -> None:
    """Since when it has been at least WARN, ERROR, or stale (kept while it stays so)."""
    shown = status.shown
    stale = status.stale or shown == STALE
    status.stale_since = (status.stale_since or at) if stale else None
    status.warn_since = (status.warn_since or at) if not stale and shown >= WARN else None
    status.error_since = (status.error_since or at) if not stale and shown >= ERROR else None


def apply_diagnostics(known: KnownRecords, fact: dict, at: datetime, applied: Applied) -> None:
    robot = known.robot(fact)
    statuses, heard, left_out = fact.get("statuses"), fact.get("heard"), fact.get("left_out", 0)
    if not isinstance(statuses, list) or len(statuses) > protocol.MAX_STATUSES_PER_FACT:
        raise GatewayInputRefused(f"statuses must be a list of at most {protocol.MAX_STATUSES_PER_FACT}")
    if not isinstance(heard, list) or len(heard) > protocol.MAX_STATUSES or not all(
            isinstance(n, str) and len(n) <= protocol.MAX_STATUS_NAME for n in heard):
        raise GatewayInputRefused(f"heard must be a list of at most {protocol.MAX_STATUSES} status names")
    if not isinstance(left_out, int) or isinstance(left_out, bool) or left_out < 0:
        raise GatewayInputRefused("left_out must be a count")
    base = robot.namespace.rstrip("/")
    topics = tuple(f"{base}/{name}" for name in protocol.DIAGNOSTIC_TOPICS)
    reports = {s["name"]: s for s in (_status(item, topics) for item in statuses)}
    changed, not_kept = _store(robot, reports, at)
    if heard:
        Status.objects.filter(robot=robot, name__in=heard, stale=False).update(heard=at)
    if left_out or not_kept:
        Intake.objects.get_or_create(robot=robot)
        Intake.objects.filter(robot=robot).update(left_out_here=F("left_out_here") + not_kept,
                                                  **({"left_out_by_gateway": left_out} if left_out else {}))
    if changed or heard:
        applied.pushes.append((page_group(robot.id), {"type": "diagnostics.changed", "names": changed[:200],
                                                 "more": len(changed) > 200 or bool(heard)}))


def _store(robot: Any, reports: dict[str, dict], at: datetime) -> tuple[list[str], int]:
    """The reports written: the names of the statuses whose level, message or key/values changed,
    and how many new ones were not kept (over MAX_STATUSES)."""
    existing = {s.name: s for s in Status.objects.filter(robot=robot, name__in=list(reports))}
    room = protocol.MAX_STATUSES - Status.objects.filter(robot=robot).count() \
        if any(name not in existing for name in reports) else 0
    new, updated, history, changed = [], [], [], []
    not_kept = 0
    for name, report in reports.items():
        heard_at = at - timedelta(seconds=report.pop("age_s"))  # (age_s is checked: not negative)
        status = existing.get(name)
        if status is None:
            if room <= 0:
                not_kept += 1
                continue
            room -= 1
            status = Status(robot=robot, heard=heard_at, level_since=heard_at, **report)
            _since(status, heard_at)
            new.append(status)
            history.append(LevelChange(robot=robot, name=name, level=status.shown, message=status.message,
                                       at=heard_at))
            changed.append(name)
            continue
        shown_before = status.shown
        for field, value in report.items():
            setattr(status, field, value)
        status.heard = heard_at  # (a stale one's report is as old as its last message)
        if status.shown != shown_before:
            when = max(at if status.stale else heard_at, status.level_since)  # (never before the last change)
            status.level_since = when
            history.append(LevelChange(robot=robot, name=name, level=status.shown, message=status.message, at=when))
        _since(status, at if status.stale else heard_at)
        updated.append(status)
        changed.append(name)
    Status.objects.bulk_create(new)
    _update(updated)
    LevelChange.objects.bulk_create(history)
    for name in {change.name for change in history} - {status.name for status in new}:
        _prune(robot, name)
    return changed, not_kept


def _update(statuses: list[Status]) -> None:
    """The rows written again, in one prepared statement run for each: a status's key/values change
    with every message (a measured frequency), so a busy fleet sends hundreds a second, and
    Django's bulk_update (a CASE per field and row) took ~4 ms per row."""
    if not statuses:
        return
    fields = [Status._meta.get_field(name) for name in FIELDS]
    quote = connection.ops.quote_name
    sql = (f"UPDATE {quote(Status._meta.db_table)} SET {', '.join(f'{quote(f.column)} = %s' for f in fields)} "
           f"WHERE {quote(Status._meta.pk.column)} = %s")
    rows = [[f.get_db_prep_save(getattr(status, f.attname), connection) for f in fields] + [status.pk]
            for status in statuses]
    with connection.cursor() as cursor:
        cursor.executemany(sql, rows)


def _prune(robot: Any, name: str) -> None:
    """At most MAX_HISTORY level changes per status: the oldest go."""
    oldest_kept = (LevelChange.objects.filter(robot=robot, name=name).order_by("-at", "-id")
                   .values_list("at", flat=True)[MAX_HISTORY - 1:MAX_HISTORY])
    cutoff = list(oldest_kept)
    if cutoff:
        LevelChange.objects.filter(robot=robot, name=name, at__lt=cutoff[0]).delete()


# The gateway says when a status goes stale; should it not (it restarted and never heard the status
# again, or it is offline), the site marks statuses not heard for this much longer stale itself.
SILENT_MARGIN_S = protocol.DIAGNOSTICS_REFRESH_S + 3.0
SILENT_BATCH = 1000


def mark_silent(now: datetime) -> list[tuple[str, dict]]:
    """Statuses not heard for the stale time and more, not marked stale by their gateway: stale now,
    on record. The pushes for the pages that show them."""
    limit = now - timedelta(seconds=settings.LIFECYCLE["DIAGNOSTICS_STALE_S"] + SILENT_MARGIN_S)
    silent = list(Status.objects.filter(stale=False, heard__lt=limit)[:SILENT_BATCH])
    history, names = [], {}
    for status in silent:
        status.stale = True
        status.level_since = max(now, status.level_since)
        history.append(LevelChange(robot_id=status.robot_id, name=status.name, level=STALE, message=status.message,
                                   at=status.level_since))
        _since(status, status.level_since)
        names.setdefault(status.robot_id, []).append(status.name)
    Status.objects.bulk_update(silent, ["stale", "level_since", "warn_since", "error_since", "stale_since"])
    LevelChange.objects.bulk_create(history)
    return [(page_group(robot_id), {"type": "diagnostics.changed", "names": found[:200], "more": len(found) > 200})
            for robot_id, found in names.items()]
