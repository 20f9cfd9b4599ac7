"""A heartbeat's times must be plausible: not before 2000, not more than MAX_CLOCK_SKEW ahead
of the site's clock. Otherwise they are left out, and such a beat is no sign of life: a beat
with "at": 9999999999 (year 2286) kept a gateway online for good and was stored as its last
beat. Through what the ingest process (copy_beats, beat_fields) and the pages and API
(gateways.statuses, describe) use, with a real Redis and the test database."""
from __future__ import annotations

import time
from datetime import datetime, timedelta, timezone

import pytest

from lifecycle_site.fleet.models import Gateway, Robot
from lifecycle_site.gateway_link import gateways
from lifecycle_site.gateway_link.stream_entries import MAX_CLOCK_SKEW, beat_fields
from lifecycle_site.ingest.management.commands.ingest import Ingest
from ros_gateway.shared import protocol
from tests import stack
from tests.gateway_part import clear_streams, forget_ingest_processes

NOW = "now"
AHEAD = "ahead"
IMPLAUSIBLE = {  # a beat's "at" (seconds since the epoch) and "started"
    "year 2286": (9_999_999_999, "2286-11-20T17:46:39+00:00"),
    "ahead by more than the skew": (AHEAD, None),  # measured when the test runs, not when collected
    "1970": (0, "1970-01-01T00:00:00+00:00"),
    "1999": (946_684_799, "1999-12-31T23:59:59Z"),
    "not a number": ("soon", "yesterday"),
    "infinite": (float("inf"), None),
}


def ahead(seconds: float) -> float:
    return time.time() + seconds


@pytest.mark.parametrize("case", IMPLAUSIBLE)
def test_implausible_times_are_left_out_of_the_gateways_row(case):
    at, started = IMPLAUSIBLE[case]
    if at == AHEAD:  # collection may be 20 minutes before the test runs in the whole suite
        at = ahead(MAX_CLOCK_SKEW.total_seconds() + 600)
    fields = beat_fields({"at": at, "started": started, "version": "2.0", "nodes": 3})
    assert "last_beat" not in fields and "started" not in fields
    assert (fields["version"], fields["node_count"]) == ("2.0", 3)  # the rest is kept


def test_a_clock_a_little_ahead_is_fine():
    at = ahead(MAX_CLOCK_SKEW.total_seconds() - 30)
    started = datetime.now(timezone.utc) + MAX_CLOCK_SKEW - timedelta(seconds=30)
    fields = beat_fields({"at": at, "started": started.isoformat()})
    assert fields["last_beat"] == datetime.fromtimestamp(at, timezone.utc) and fields["started"] == started


@pytest.fixture
def cell(transactional_db, redis_server, live_ingest_set_aside) -> Gateway:
    forget_ingest_processes()
    clear_streams("cell-t")
    row = Gateway.objects.create(name="cell-t")
    Robot.objects.create(name="time-agv", domain_id=43, gateway=row)
    return row


def test_the_ingest_process_does_not_store_a_beat_from_2286(cell):
    earlier = datetime.now(timezone.utc) - timedelta(hours=1)
    Gateway.objects.filter(pk=cell.pk).update(last_beat=earlier)
    stack.write_beat("cell-t", at=9_999_999_999, started="2286-11-20T17:46:39+00:00", version="6.6.6")
    ingest = Ingest()
    assert ingest.hold_lease()
    ingest.refresh()
    ingest.copy_beats()
    row = Gateway.objects.get(pk=cell.pk)
    assert (row.last_beat, row.started, row.version) == (earlier, None, "6.6.6")


def test_a_beat_from_2286_is_no_sign_of_life_for_pages_and_the_api(cell, viewer_client):
    stack.write_beat("cell-t", at=9_999_999_999, started="2286-11-20T17:46:39+00:00")
    state = gateways.status("cell-t")
    assert (state.online, state.state, state.last_beat) == (False, gateways.NEVER, None)
    # known from an earlier, plausible beat: offline since then
    earlier = datetime.now(timezone.utc) - timedelta(hours=3)
    Gateway.objects.filter(pk=cell.pk).update(last_beat=earlier, started=earlier - timedelta(days=1))
    listed = {g["name"]: g for g in viewer_client.get("/api/v1/gateways").json()["gateways"]}["cell-t"]
    assert (listed["online"], listed["status"], listed["last_beat"]) == (False, "offline", earlier.isoformat())
    assert listed["reason"].startswith("no heartbeat since ") and listed["reason"].endswith("3 h ago")
    # that beat is ignored as a whole: what the row kept from the earlier one
    assert listed["started"] == (earlier - timedelta(days=1)).isoformat()
    robot = {r["name"]: r for r in viewer_client.get("/api/v1/robots").json()["robots"]}["time-agv"]
    assert robot["gateway_online"] is False
    page = viewer_client.get("/").content.decode()
    head = page[page.index('id="gateway-cell-t-head"'):page.index("</header>", page.index('id="gateway-cell-t"'))]
    assert 'data-gateway-online="false"' in head and "2286" not in page


def test_a_row_stored_with_a_time_from_2286_is_not_believed_either(cell):
    """What the ingest process stored before times were checked."""
    Gateway.objects.filter(pk=cell.pk).update(last_beat=datetime(2286, 11, 20, tzinfo=timezone.utc))
    stack.redis_client().delete(protocol.beat_key(gateways.channel_prefix(), "cell-t"))
    gateways.forget()
    (state,) = gateways.statuses([Gateway.objects.get(pk=cell.pk)])
    assert (state.state, state.last_beat) == (gateways.NEVER, None)
    stack.write_beat("cell-t", started="2286-11-20T17:46:39+00:00")  # at the right time: online again
    assert gateways.status("cell-t").online
    view = gateways.describe(Gateway.objects.get(pk=cell.pk), gateways.status("cell-t"))
    assert view["online"] and view["started"] is None  # its "started" is not believed
