"""What the state timeline shows besides states (issue 26, item 7): the windows it offers (15
minutes, a range of one's own), the marks of crashes, restarts, failed transitions and gateway
outages with their links, the outages the ingest process records, the drawing's positions
as shares of the page's width, and the log console opened at a moment."""
from __future__ import annotations

import json
from datetime import datetime, timedelta, timezone
from urllib.parse import parse_qs, urlsplit

import pytest

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.dashboard import timeline_drawing as td
from lifecycle_site.fleet.models import Gateway, GatewayOutage, LogRecord, ManagedNode, Robot
from lifecycle_site.gateway_link import gateways as gw
from lifecycle_site.ingest import outages
from lifecycle_site.timelines import events as te
from lifecycle_site.timelines import node as tl
from lifecycle_site.timelines import windows as tw
from lifecycle_site.timelines.robot import robot_timeline
from ros_gateway.shared import state_machine as sm

NOW = datetime(2026, 11, 23, 12, 0, tzinfo=timezone.utc)


def ago(minutes: float) -> datetime:
    return NOW - timedelta(minutes=minutes)


@pytest.fixture
def node(db) -> ManagedNode:
    robot = Robot.objects.create(name="ev-agv", domain_id=64)
    return ManagedNode.objects.create(robot=robot, name="/flaky", alive=True, state_id=sm.UNCONFIGURED,
                                      state_label="unconfigured", first_seen=ago(60 * 24), last_seen=NOW,
                                      state_changed=ago(60 * 24))


def record(node: ManagedNode, minutes_ago: float, outcome: str, error: str = "", label: str = "configure"):
    at = ago(minutes_ago)
    return TransitionRecord.objects.create(
        node=node, robot=node.robot, robot_name=node.robot.name, node_name=node.name, transition_label=label,
        start_state_id=sm.UNCONFIGURED, result_state_id=sm.UNCONFIGURED if outcome == "failed" else None,
        outcome=outcome, source="api", requested_at=at, completed_at=at, duration_ms=0.0, error=error)


def test_the_windows_offered_and_a_range_of_ones_own():
    assert tw.parse({"window": "15min"}, NOW) == tw.Window("15min", ago(15), NOW)
    assert tw.parse({}, NOW).name == "day"
    window = tw.parse({"from": "2026-11-23T10:00", "to": "2026-11-23T11:30"}, NOW)
    assert (window.name, window.start, window.end) == ("custom", ago(120), ago(30))
    assert window.query == "from=2026-11-23T10%3A00&to=2026-11-23T11%3A30"
    # A range cannot end in the future (it ends now), nor be empty, backwards or longer than 31 days.
    assert tw.parse({"from": "2026-11-23T11:00", "to": "2026-11-24T00:00"}, NOW).end == NOW
    assert tw.parse({"from": "2026-11-23T11:00"}, NOW).end == NOW
    for query, why in [({"from": "2026-11-23T11:00", "to": "2026-11-23T10:00"}, "at least a minute"),
                       ({"from": "2026-09-01T00:00", "to": "2026-11-23T00:00"}, "at most 31 days"),
                       ({"from": "yesterday"}, "Not a date and time"), ({"window": "year"}, "no window 'year'")]:
        with pytest.raises(tw.WindowError, match=why):
            tw.parse(query, NOW)
    shown, warning = tw.page_window({"window": "year"}, NOW)
    assert shown.name == "day" and warning.endswith("Showing the last day.")


def test_failures_crashes_and_restarts_are_marked_with_the_nodes_reason(node):
    record(node, 50, "succeeded")
    failed = record(node, 40, "failed", "The node's on_configure callback returned FAILURE. The node said: no lidar")
    record(node, 30, "process_lost", "its process ended (exit code 3)", label="")
    record(node, 20, "process_restarted", label="")
    record(node, 10, "timed_out", "x" * 1000)
    timeline = tl.node_timeline(node, "hour", now=NOW)
    assert [(e.kind, e.title) for e in timeline.events] == [
        ("failed", "failed transition (configure)"), ("process_lost", "crash"), ("process_restarted", "restart"),
        ("timed_out", "transition timed out (configure)")]
    first = timeline.events[0]
    assert first.record_id == failed.id and first.reason.endswith("The node said: no lidar")
    assert len(timeline.events[-1].reason) == te.MAX_REASON  # the audit record keeps it whole
    # Its audit record (that second, that outcome) and the node's log at that moment.
    audit = parse_qs(urlsplit(first.audit_url).query)
    assert audit == {"robot": ["ev-agv"], "node": ["/flaky"], "outcome": ["failed"],
                     "since": ["2026-11-23T11:20:00"], "until": ["2026-11-23T11:20:01"]}
    assert first.logs_url == f"/logs/node/{node.key}/?at=2026-11-23T11:20:00.000000Z"
    assert [e["kind"] for e in timeline.as_dict()["events"]] == ["failed", "process_lost", "process_restarted",
                                                                 "timed_out"]
    # Only the newest are read again for their reason, however many the window holds.
    capped = te.record_events(((node, r.requested_at, r.outcome, r.id) for r in TransitionRecord.objects.all()), 2)
    assert [e.kind for e in capped] == ["process_restarted", "timed_out"]


def test_gateway_outages_overlapping_the_window_are_marked(node):
    local = node.robot.gateway
    GatewayOutage.objects.create(gateway=local, began=ago(200), ended=ago(100), reason="offline")  # before
    GatewayOutage.objects.create(gateway=local, began=ago(70), ended=ago(50), reason="offline")
    GatewayOutage.objects.create(gateway=local, began=ago(5), reason="quarantined")  # still
    other = Gateway.objects.create(name="cell-z")
    GatewayOutage.objects.create(gateway=other, began=ago(30), ended=ago(20))  # another gateway's
    timeline = tl.node_timeline(node, "hour", now=NOW)
    assert [(e.at, e.until) for e in timeline.outages] == [(ago(70), ago(50)), (ago(5), None)]
    assert timeline.outages[1].reason == te.OUTAGE_REASONS["quarantined"]
    assert parse_qs(urlsplit(timeline.outages[0].audit_url).query)["until"] == ["2026-11-23T11:10:01"]
    assert timeline.outages[0].logs_url.startswith("/logs/robot/ev-agv/?at=")
    assert [e.at for e in robot_timeline(node.robot, "hour", now=NOW).outages] == [ago(70), ago(5)]
    # A node first seen after an outage ended was not hidden by it: its page leaves it out.
    ManagedNode.objects.filter(pk=node.pk).update(first_seen=ago(40))
    node.refresh_from_db()
    assert [e.at for e in tl.node_timeline(node, "hour", now=NOW).outages] == [ago(5)]


def test_the_ingest_opens_an_outage_when_it_sees_a_gateway_down_and_closes_it_when_back(db, monkeypatch):
    row = Gateway.objects.create(name="cell-y")
    seen: list[gw.GatewayStatus] = []
    monkeypatch.setattr(gw, "statuses", lambda rows: [seen[-1] for _ in rows])
    seen.append(gw.GatewayStatus("cell-y", gw.OFFLINE, ago(3)))
    outages.observe([row], now=NOW)
    outages.observe([row], now=NOW)  # seen twice: still one
    assert list(GatewayOutage.objects.values_list("began", "ended", "reason")) == [(ago(3), None, "offline")]
    seen.append(gw.GatewayStatus("cell-y", gw.ONLINE, ago(1)))
    outages.observe([row], now=NOW)
    assert list(GatewayOutage.objects.values_list("began", "ended")) == [(ago(3), ago(1))]
    # Redis unreachable says nothing of the gateway; a quarantine begins when the site cut it off.
    seen.append(gw.GatewayStatus("cell-y", gw.UNREACHABLE, ago(1)))
    outages.observe([row], now=NOW)
    seen.append(gw.GatewayStatus("cell-y", gw.QUARANTINED, NOW, quarantined=ago(0.5)))
    outages.observe([row], now=NOW)
    assert GatewayOutage.objects.filter(ended__isnull=True).get().began == ago(0.5)


def test_the_drawing_places_by_share_of_the_width_and_ticks_any_range(node):
    record(node, 30, "failed", "no")
    window = tw.Window("custom", ago(90), NOW)
    timeline = tl.node_timeline(node, window)
    drawn = td.drawing(window.start, window.end, [timeline], False, td.numbered(timeline.events))
    marks = str(drawn["lanes"][0]["marks"])
    assert 'href="#ev-0"' in marks and 'x="66.667%"' in marks  # 60 of 90 minutes
    assert 'width="100.000%"' in str(drawn["lanes"][0]["bars"])
    assert td.tick_step(timedelta(minutes=15)) == timedelta(minutes=2)
    assert td.tick_step(timedelta(days=3)) == timedelta(hours=12)
    assert [t.time for t in td.ticks(window.start, window.end)][:3] == ["10:30", "10:40", "10:50"]
    # A state's name is written where it fits on a phone; on wide screens only where it fits there.
    assert td.Bar(0, 20, 0, "inactive", NOW, NOW).label_class() == ""
    assert td.Bar(0, 8, 0, "inactive", NOW, NOW).label_class() == "tl-wide"
    assert td.Bar(0, 2, 0, "inactive", NOW, NOW).label_class() is None


def test_the_log_console_opens_at_a_moment(viewer_client, node):
    for second in range(0, 600, 2):  # a line every 2 s over 10 minutes
        LogRecord.objects.create(robot=node.robot, node=node, logger="flaky", level=20, message=f"line {second}",
                                 stamp=ago(10) + timedelta(seconds=second))
    page = viewer_client.get(f"/logs/node/{node.key}/", {"at": ago(5).isoformat()}).content.decode()
    history = json.loads(page.split('id="log-history" type="application/json">', 1)[1].split("</script>", 1)[0])
    messages = [r["message"] for r in history]
    assert len(messages) == 300 and "line 300" in messages  # the moment is 5 minutes in
    assert 'data-at="2026-11-23T11:55:00+00:00"' in page and "The lines around 2026-11-23 11:55:00 UTC" in page
    assert history == sorted(history, key=lambda r: r["id"])  # in the order they came, as the console shows


def test_the_api_takes_a_range_and_says_what_is_wrong_with_one(viewer_client, node):
    body = viewer_client.get(f"/api/v1/nodes/{node.key}/timeline",
                             {"from": "2026-11-23T10:00", "to": "2026-11-23T11:30"}).json()
    assert body["window"] == {"name": "custom", "start": "2026-11-23T10:00:00+00:00",
                              "end": "2026-11-23T11:30:00+00:00"}
    assert viewer_client.get(f"/api/v1/robots/{node.robot.name}/timeline", {"window": "15min"}).json()[
        "window"]["name"] == "15min"
    refused = viewer_client.get(f"/api/v1/nodes/{node.key}/timeline", {"from": "2026-11-23T11:00",
                                                                      "to": "2026-11-23T10:00"})
    assert refused.status_code == 400 and refused.json()["error"]["code"] == "invalid_field"
    assert "at least a minute" in refused.json()["error"]["message"]
