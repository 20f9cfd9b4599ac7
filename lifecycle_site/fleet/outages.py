"""Gateway outages: stretches in which no process of a gateway ran, so that nothing received its
robots' /rosout (the log consoles mark them). A process that stops, or is killed, and another
that starts: from the last heartbeat of the one to the start of the other. Seen by the ingest
process (ingest_duties.SiteDuties.copy_beats) when the new process's first heartbeat comes.

A gateway that was only silent (Redis away, frozen) is not recorded here: its process went on
and held what it received (what it had to drop, its heartbeat counts: outbox, logs_dropped)."""
from __future__ import annotations

from datetime import datetime, timedelta

from django.utils import timezone

from lifecycle_site.fleet.absences import ABSENCE_KEEP_DAYS
from lifecycle_site.fleet.models import Gateway, GatewayOutage
from lifecycle_site.fleet.stream_entries import beat_started

MAX_LISTED = 50


def note_restart(row: Gateway, beat: dict) -> GatewayOutage | None:
    """Record the outage a heartbeat reveals, if any: one from another process (``instance``)
    than the row last copied, which started after that one's last heartbeat. Call it before the
    beat is copied into ``row``'s database row."""
    instance = beat.get("instance")
    started = beat_started(beat.get("started"))
    if (not isinstance(instance, str) or not row.instance or instance[:32] == row.instance
            or row.last_beat is None or started is None or started <= row.last_beat):
        return None
    return GatewayOutage.objects.create(gateway=row, began=row.last_beat, ended=started)


def recent(gateway: str, since: datetime | None = None) -> list[dict]:
    """The gateway's outages that ended after ``since`` (default: ABSENCE_KEEP_DAYS), oldest
    first, at most MAX_LISTED (the newest)."""
    since = since or timezone.now() - timedelta(days=ABSENCE_KEEP_DAYS)
    rows = GatewayOutage.objects.select_related("gateway").filter(gateway__name=gateway, ended__gte=since)
    return [row.as_dict() for row in reversed(rows.order_by("-ended")[:MAX_LISTED])]


def prune(keep_days: float = ABSENCE_KEEP_DAYS) -> int:
    deleted, _ = GatewayOutage.objects.filter(ended__lt=timezone.now() - timedelta(days=keep_days)).delete()
    return deleted
