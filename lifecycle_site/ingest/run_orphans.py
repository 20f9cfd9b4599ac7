"""Runs whose gateway went silent for good end failed (the ingest process's leader looks every few
seconds), with the verdict published first so that a gateway that comes back does not go on."""
from __future__ import annotations

import logging
from datetime import datetime, timedelta, timezone

from django.conf import settings

from lifecycle_site.fleet.models import Gateway, GroupRun
from lifecycle_site.gateway_link import gateways
from lifecycle_site.ingest import verdicts

log = logging.getLogger(__name__)


def fail_runs_of_silent_gateways() -> None:
    """Runs of a gateway that has been silent past LIFECYCLE_RUN_ORPHAN_AFTER, with nothing
    of it left to store, end failed: a killed gateway that stays away would otherwise leave
    them running for good (one that comes back settles them itself, gateway.started).

    The verdict goes to the gateway first (verdicts.py): one that was only frozen or cut off
    and comes back reads it before its next step and stops, instead of finishing a run the
    site has called failed."""
    open_states = (GroupRun.Status.QUEUED, GroupRun.Status.RUNNING)
    names = set(GroupRun.objects.filter(status__in=open_states).values_list("robot__gateway__name", flat=True))
    if not names:
        return
    now = datetime.now(timezone.utc)
    after = timedelta(seconds=settings.LIFECYCLE["RUN_ORPHAN_AFTER"])
    rows = list(Gateway.objects.filter(name__in=names))
    for row, state in zip(rows, gateways.statuses(rows), strict=True):
        if state.online or state.last_beat is None or now - state.last_beat < after or row.backlog:
            continue
        ids = list(GroupRun.objects.filter(robot__gateway=row, status__in=open_states).values_list("id", flat=True))
        message = (f"the gateway {row.name} has been silent since {state.last_beat:%Y-%m-%d %H:%M:%S} UTC, "
                   "so the run could not finish; what finished before is on record")
        verdicts.publish(row.name, ids, GroupRun.Status.FAILED, message, now)
        settled = GroupRun.objects.filter(id__in=ids, status__in=open_states).update(
            status=GroupRun.Status.FAILED, finished=now, message=message)
        if settled:
            log.warning("gateway %s: %d run(s) failed, the gateway is silent since %s", row.name, settled,
                        state.last_beat.isoformat())
