"""Diagnostics on real parts: DiagnosticArray publishers of the test (rclpy processes in the robot's
namespace, on /diagnostics and an aggregator's /diagnostics_agg), the gateway, the ingest process
and the site's database. The tree, the node that reports a status, staleness, the history of level
changes, the alert rule, /metrics and the JSON API are asserted on what they produced."""
from __future__ import annotations

import time

import pytest

from lifecycle_site.alerts.models import Alert, Rule
from lifecycle_site.diagnostics.models import LevelChange, Status
from lifecycle_site.fleet.models import Robot
from tests import stack
from tests.integration.conftest import register
from tests.integration.diagnostics_publisher import Source

ROBOT = "it-diag"
NAMESPACE = "/dg"
DOMAIN_OFFSET = 40
AGG = ["/DG", "/DG/Sensors", "/DG/Sensors/Lidar", "/DG/Power", "/DG/Power/Battery"]


@pytest.fixture(scope="module")
def sources(gateway):
    register(ROBOT, stack.domain(DOMAIN_OFFSET), NAMESPACE)
    env = stack.environment()
    raw = Source(stack.domain(DOMAIN_OFFSET), env, "--namespace", NAMESPACE, "--statuses", "3", "--rate", "2")
    agg = Source(stack.domain(DOMAIN_OFFSET), env, "--namespace", NAMESPACE, "--node", "aggregator",
                 "--topic", "diagnostics_agg", "--statuses", "0", "--rate", "2")
    try:
        for name in AGG:
            agg.send(name=name, level=0, message="fine", values=[["path", name]])
        yield raw, agg
    finally:
        raw.stop()
        agg.stop()
        Robot.objects.filter(name=ROBOT).update(enabled=False)


def status(name: str) -> Status | None:
    return Status.objects.filter(robot__name=ROBOT, name=name).first()


def wait_status(name: str, timeout: float = 20, **expect) -> Status:
    def found():
        row = status(name)
        return row if row is not None and all(getattr(row, k) == v for k, v in expect.items()) else None

    return stack.wait_for(found, timeout, f"status {name!r} with {expect}")


def test_statuses_arrive_with_their_reporting_node_and_the_tree_sums_up(api, sources):
    raw, agg = sources
    first = wait_status("diag_source: check 0")
    assert first.level == 0 and first.message == "fine" and first.hardware_id == "hw0"
    assert first.values == [["index", "0"]] and first.topic == f"{NAMESPACE}/diagnostics"
    wait_status("diag_source: check 0", node=f"{NAMESPACE}/diag_source")  # its publisher, from the graph
    for name in AGG:
        wait_status(name, topic=f"{NAMESPACE}/diagnostics_agg")
    # An aggregated status keeps the hardware id of the status it sums up: so it has its node.
    agg.send(name="/DG/Sensors/Lidar", level=0, message="fine", hardware_id="hw0")
    wait_status("/DG/Sensors/Lidar", node=f"{NAMESPACE}/diag_source")
    assert status("/DG/Sensors").node == ""  # the aggregator's own summary: no node

    agg.send(name="/DG/Sensors/Lidar", level=1, message="scan rate low", values=[["frequency_hz", "4.1"]])
    wait_status("/DG/Sensors/Lidar", level=1, message="scan rate low")
    page = api.get(f"/robots/{ROBOT}/diagnostics/")
    assert page.status_code == 200
    html = page.content.decode()
    assert "scan rate low" in html and "Lidar" in html and "diag_source: check 2" in html
    # The branch above shows the worst below it (its own status says OK).
    body = api.get(f"/api/v1/robots/{ROBOT}/diagnostics").json()
    rows = {row["path"]: row for row in body["tree"]}
    assert rows["/DG/Sensors"]["shown"] == "WARN" and rows["/DG/Sensors"]["status"]["level"] == "OK"
    assert rows["/DG"]["shown"] == "WARN" and rows["/DG/Sensors/Lidar"]["depth"] == 2
    assert body["counts"]["WARN"] == 1


def test_level_changes_are_history_and_a_silent_status_goes_stale(api, sources):
    raw, agg = sources
    name = "diag_source: check 1"
    wait_status(name, level=0)
    raw.send(name=name, level=1, message="getting warm", values=[["temp", "71"]])
    wait_status(name, level=1)
    raw.send(name=name, level=2, message="too hot", values=[["temp", "93"]])
    row = wait_status(name, level=2, message="too hot")
    assert row.values == [["temp", "93"]] and row.error_since is not None and row.warn_since <= row.error_since
    raw.send(drop=name)
    began = time.monotonic()
    row = wait_status(name, timeout=15, stale=True)
    assert time.monotonic() - began >= 3  # not before the stale time (5 s since last heard)
    assert row.message == "too hot" and row.stale_since is not None and row.error_since is None
    levels = list(LevelChange.objects.filter(robot__name=ROBOT, name=name).order_by("at", "id")
                  .values_list("level", flat=True))
    assert levels[-3:] == [1, 2, 3], levels
    history = api.get(f"/api/v1/robots/{ROBOT}/diagnostics/history", {"name": name}).json()
    assert [c["level"] for c in history["changes"][:3]] == ["STALE", "ERROR", "WARN"]
    page = api.get(f"/robots/{ROBOT}/diagnostics/status", {"name": name})
    assert page.status_code == 200 and "too hot" in page.content.decode() and "STALE" in page.content.decode()
    raw.send(name=name, level=0, message="fine again")  # heard again: no longer stale
    row = wait_status(name, stale=False, level=0)
    assert row.stale_since is None


def test_an_alert_rule_fires_on_a_status_at_or_above_a_level_for_a_while_and_on_stale(api, sources):
    raw, agg = sources
    rule = Rule.objects.create(name="lidar error", kind=Rule.Kind.DIAGNOSTIC, status_pattern="/DG/Sensors",
                               level="error", for_seconds=1.0, robot=Robot.objects.get(name=ROBOT))
    stale_rule = Rule.objects.create(name="diag stale", kind=Rule.Kind.DIAGNOSTIC,
                                     status_pattern="diag_source: *", level="stale")
    try:
        agg.send(name="/DG/Sensors/Lidar", level=2, message="no scans for 2 s")
        fired = stack.wait_for(lambda: Alert.objects.filter(rule=rule, status=Alert.Status.FIRING).first(), 20,
                               "the diagnostic alert")
        assert "/DG/Sensors/Lidar" in fired.summary and "ERROR" in fired.summary and "no scans" in fired.summary
        raw.send(drop="diag_source: check 2")
        stale = stack.wait_for(lambda: Alert.objects.filter(rule=stale_rule, status=Alert.Status.FIRING).first(),
                               25, "the stale alert")
        assert "diag_source: check 2" in stale.summary and "stale" in stale.summary
        agg.send(name="/DG/Sensors/Lidar", level=0, message="fine")
        stack.wait_for(lambda: Alert.objects.filter(rule=rule, status=Alert.Status.RESOLVED).exists(), 20,
                       "the alert resolved")
    finally:
        rule.delete()
        stale_rule.delete()


def test_metrics_have_a_gauge_per_status_and_counts_per_level(api, sources):
    wait_status("/DG/Power/Battery")
    text = api.get("/metrics").content.decode()
    assert f'lifecycle_diagnostic_level{{name="/DG/Power/Battery",robot="{ROBOT}"}} 0.0' in text, text[-3000:]
    assert f'lifecycle_diagnostic_statuses{{level="ok",robot="{ROBOT}"}}' in text
    assert "lifecycle_diagnostic_series_left_out" in text


def test_the_api_answers_bad_requests_in_words(api, sources):
    missing = api.get(f"/api/v1/robots/{ROBOT}/diagnostics/history")
    assert missing.status_code == 400 and missing.json()["error"]["code"] == "missing_field"
    unknown = api.get(f"/api/v1/robots/{ROBOT}/diagnostics/history", {"name": "no such"})
    assert unknown.status_code == 404 and "no diagnostic status named 'no such'" in unknown.json()["error"]["message"]
    limit = api.get(f"/api/v1/robots/{ROBOT}/diagnostics/history", {"name": "/DG", "limit": "lots"})
    assert limit.status_code == 400 and limit.json()["error"]["code"] == "invalid_field"
    assert api.get("/api/v1/robots/nobody/diagnostics").status_code == 404
    page = api.get(f"/robots/{ROBOT}/diagnostics/status", {"name": "no such"})
    assert page.status_code == 404


def test_the_cli_prints_the_tree_and_exits_1_while_a_status_is_in_error(sources):
    from tests.integration.test_cli import cli

    raw, agg = sources
    agg.send(name="/DG/Power/Battery", level=0, message="82 %")
    wait_status("/DG/Power/Battery", level=0, message="82 %")
    Status.objects.filter(robot__name=ROBOT, level=2).update(level=0)  # as if all were fine
    Status.objects.filter(robot__name=ROBOT, stale=True).update(stale=False)
    done = cli("diagnostics", ROBOT)
    assert done.code == 0, done.err
    battery = next(line for line in done.lines if "Battery:" in line)
    assert battery.startswith("    OK     Battery: 82 % (") and "s ago)" in battery  # depth 2, indented

    agg.send(name="/DG/Power/Battery", level=2, message="9 %")
    wait_status("/DG/Power/Battery", level=2)
    problems = cli("diagnostics", ROBOT, "--problems")
    assert problems.code == 1
    assert [line.split()[0] for line in problems.lines] == ["ERROR"] * 3  # /DG, /DG/Power, Battery
    assert "Battery: 9 %" in problems.out
    as_json = cli("diagnostics", ROBOT, "--json", "--problems")
    assert as_json.code == 1 and '"shown": "ERROR"' in as_json.out
    assert cli("diagnostics", "nobody").code == 2
