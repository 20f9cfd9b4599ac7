"""When gateways could take no commands: an outage is opened when the ingest process (its
leader, every few seconds) sees a gateway offline, stopped or quarantined, and closed when it
sees it online again; and, for a restart too quick to be seen offline, when a new process's
first heartbeat comes (``note_restart``). The state timeline marks them
(timelines/events.py), and the log consoles: nothing received the robots' /rosout then.

It begins at the gateway's last heartbeat (its last sign of life; for a quarantine, when the
site cut it off) and ends at the first heartbeat seen after it. Only what the site saw is
recorded: a gateway silent while no ingest process ran has an outage from the first look
after, and a Redis the site cannot reach says nothing about any gateway (none is opened or
closed). A gateway has at most one open outage, so two ingest processes looking at once open
it once.
"""
from __future__ import annotations

from datetime import datetime, timedelta
from typing import Iterable

from django.db import IntegrityError, transaction
from django.db.models import Q
from django.utils import timezone

from lifecycle_site.fleet.models import Gateway, GatewayOutage
from lifecycle_site.gateway_link import gateways as gw
from lifecycle_site.gateway_link.stream_entries import beat_started

OUTAGE_KEEP_DAYS = 30  # as absences (ingest/absences.py): longer than a timeline's widest window
DOWN = (gw.OFFLINE, gw.STOPPED, gw.QUARANTINED)
MAX_LISTED = 50
RESTARTED = "restarted"


def observe(rows: Iterable[Gateway], now: datetime | None = None) -> None:
    """Open an outage for each of these gateways that is down and has none open, and close the
    open one of each that is online."""
    rows = list(rows)
    if not rows:
        return
    now = now or timezone.now()
    open_ids = set(GatewayOutage.objects.filter(gateway__in=rows, ended__isnull=True)
                   .values_list("gateway_id", flat=True))
    for row, status in zip(rows, gw.statuses(rows), strict=True):
        if status.state in DOWN and row.pk not in open_ids:
            began = status.quarantined if status.state == gw.QUARANTINED and status.quarantined else status.last_beat
            _open(row, min(began or now, now), status.state)
        elif status.online and row.pk in open_ids:
            for outage in GatewayOutage.objects.filter(gateway=row, ended__isnull=True):
                outage.ended = max(status.last_beat or now, outage.began)
                outage.save(update_fields=["ended"])


def _open(row: Gateway, began: datetime, reason: str) -> None:
    try:
        with transaction.atomic():  # a savepoint: another ingest process opened it first, which is fine
            GatewayOutage.objects.create(gateway=row, began=began, reason=reason)
    except IntegrityError:
        pass


def note_restart(row: Gateway, beat: dict) -> GatewayOutage | None:
    """The outage a heartbeat reveals: one of another process (``instance``) than the row last
    copied, started after that one's last heartbeat, where no outage was seen (a restart within
    the seconds between two looks). Call it before the beat is copied into ``row``'s row."""
    instance = beat.get("instance")
    started = beat_started(beat.get("started"))
    if (not isinstance(instance, str) or not row.instance or instance[:32] == row.instance
            or row.last_beat is None or started is None or started <= row.last_beat):
        return None
    if GatewayOutage.objects.filter(gateway=row, began__lte=started).filter(
            Q(ended__isnull=True) | Q(ended__gte=row.last_beat)).exists():
        return None
    return GatewayOutage.objects.create(gateway=row, began=row.last_beat, ended=started, reason=RESTARTED)


def recent(gateway: str, since: datetime | None = None) -> list[dict]:
    """The gateway's outages that ended after ``since`` (or still last), oldest first, at most
    MAX_LISTED (the newest)."""
    since = since or timezone.now() - timedelta(days=OUTAGE_KEEP_DAYS)
    rows = GatewayOutage.objects.select_related("gateway").filter(gateway__name=gateway).filter(
        Q(ended__isnull=True) | Q(ended__gte=since))
    return [row.as_dict() for row in reversed(rows.order_by("-began")[:MAX_LISTED])]


def prune_outages(keep_days: float = OUTAGE_KEEP_DAYS) -> int:
    """Delete outages that ended more than ``keep_days`` ago."""
    deleted, _ = GatewayOutage.objects.filter(ended__lt=timezone.now() - timedelta(days=keep_days)).delete()
    return deleted
