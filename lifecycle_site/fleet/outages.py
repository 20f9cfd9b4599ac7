"""When gateways could take no commands: an outage is opened when the ingest process (its
leader, every few seconds) sees a gateway offline, stopped or quarantined, and closed when it
sees it online again. The state timeline marks them (dashboard/timeline_events.py).

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
from django.utils import timezone

from lifecycle_site.fleet import gateways as gw
from lifecycle_site.fleet.models import Gateway, GatewayOutage

OUTAGE_KEEP_DAYS = 30  # as absences (fleet/absences.py): longer than a timeline's widest window
DOWN = (gw.OFFLINE, gw.STOPPED, gw.QUARANTINED)


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


def prune_outages(keep_days: float = OUTAGE_KEEP_DAYS) -> int:
    """Delete outages that ended more than ``keep_days`` ago."""
    deleted, _ = GatewayOutage.objects.filter(ended__lt=timezone.now() - timedelta(days=keep_days)).delete()
    return deleted
