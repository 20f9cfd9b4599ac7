"""When nodes were away: opened by node.gone (or a robot's node list without the node), closed
by the node's return. The state timeline reads them (timelines/node.py).

Applying a fact twice, or late, changes nothing: a node has at most one open absence (a
partial unique constraint), an absence is opened only for a node that had been seen, and a
return closes only absences that began before it.
"""
from __future__ import annotations

from datetime import datetime, timedelta
from typing import Iterable

from django.db import IntegrityError, transaction
from django.utils import timezone

from lifecycle_site.fleet.models import ManagedNode, NodeAbsence

# Longer than the widest timeline window (a week), so every window it can show is complete.
ABSENCE_KEEP_DAYS = 30
# A later node.gone of an absence already open says more, never less: a lost process is more
# than a process that does not answer, which is more than a node that left. Applied in any
# order, or twice, the facts leave the same reason.
REASON_RANK = ["", "unreachable", "process_lost"]


def node_left(node_ids: Iterable[int], at: datetime, reason: str = "") -> None:
    """The nodes were not running from ``at`` on (nodes already away keep their absence, with the
    stronger of the two reasons)."""
    # A node pinned by name and never seen was not "away".
    ids = list(ManagedNode.objects.filter(id__in=list(node_ids), first_seen__isnull=False).values_list("id", flat=True))
    if not ids:
        return
    open_ids = set(NodeAbsence.objects.filter(node_id__in=ids, back_at__isnull=True).values_list("node_id", flat=True))
    weaker = REASON_RANK[:REASON_RANK.index(reason)] if reason in REASON_RANK else []
    if weaker and open_ids:
        NodeAbsence.objects.filter(node_id__in=open_ids, back_at__isnull=True, reason__in=weaker).update(reason=reason)
    new = [NodeAbsence(node_id=i, gone_at=at, reason=reason) for i in ids if i not in open_ids]
    if not new:
        return
    try:
        with transaction.atomic():  # a savepoint: a concurrent opener won the race, which is fine
            NodeAbsence.objects.bulk_create(new)
    except IntegrityError:
        for absence in new:
            with transaction.atomic():
                try:
                    absence.save()
                except IntegrityError:
                    pass  # already open


def node_back(node_ids: Iterable[int], at: datetime) -> None:
    """The nodes were running again at ``at``."""
    ids = list(node_ids)
    if ids:
        NodeAbsence.objects.filter(node_id__in=ids, back_at__isnull=True, gone_at__lte=at).update(back_at=at)


def prune_absences(keep_days: float = ABSENCE_KEEP_DAYS) -> int:
    """Delete absences that ended more than ``keep_days`` ago."""
    deleted, _ = NodeAbsence.objects.filter(back_at__lt=timezone.now() - timedelta(days=keep_days)).delete()
    return deleted
