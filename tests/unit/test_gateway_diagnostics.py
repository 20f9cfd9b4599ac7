"""The gateway's diagnostics (ros_gateway/diagnostics.py) between the messages it takes and the
facts it sends: changes sent at once, key/values and freshness at most every refresh, stale after
the site's time, text and key/values cut, statuses per robot bounded and the rest counted, the node
that reports a status found as diagnostic_updater names it."""
from __future__ import annotations

import json

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from ros_gateway import diagnostics
from ros_gateway.diagnostics import _Robot
from ros_gateway.registry import RobotInfo
from ros_gateway.shared import protocol

TOPIC = "/r1/diagnostics"


def array(*statuses: tuple) -> DiagnosticArray:
    return DiagnosticArray(status=[
        DiagnosticStatus(name=name, level=bytes([level]), message=message,
                         values=[KeyValue(key=k, value=v) for k, v in values])
        for name, level, message, values in statuses])


def robot() -> _Robot:
    return _Robot(RobotInfo(1, "r1", 7, "/r1"))


def test_topics_are_the_namespaces():
    assert robot().topics() == ["/r1/diagnostics", "/r1/diagnostics_agg"]
    assert _Robot(RobotInfo(2, "r2", 7, "")).topics() == ["/diagnostics", "/diagnostics_agg"]


def test_a_level_change_wakes_at_once_values_wait_for_the_refresh(monkeypatch):
    r, woken = robot(), []
    clock = [100.0]
    monkeypatch.setattr(diagnostics.time, "monotonic", lambda: clock[0])
    r.take(array(("lidar: scan", 0, "ok", [("hz", "10")])), TOPIC, lambda: woken.append(1))
    assert woken == [1]
    sent, heard, urgent = r.due(clock[0], 5.0)
    assert [name for name, _ in sent] == ["lidar: scan"] and urgent
    clock[0] += 0.5
    r.take(array(("lidar: scan", 0, "ok", [("hz", "9.8")])), TOPIC, lambda: woken.append(2))
    assert woken == [1]  # only the values moved
    assert r.due(clock[0], 5.0)[0] == []  # not before the refresh
    clock[0] += protocol.DIAGNOSTICS_REFRESH_S
    sent, _, urgent = r.due(clock[0], 5.0)
    assert sent[0][1].values == (("hz", "9.8"),) and not urgent
    r.take(array(("lidar: scan", 2, "no scans", [])), TOPIC, lambda: woken.append(3))
    assert woken == [1, 3] and r.due(clock[0], 5.0)[0][0][1].level == 2  # at once, whatever the refresh
    # Heard unchanged: only its name, at most every refresh.
    clock[0] += protocol.DIAGNOSTICS_REFRESH_S
    r.take(array(("lidar: scan", 2, "no scans", [])), TOPIC, lambda: None)
    assert r.due(clock[0], 5.0)[:2] == ([], ["lidar: scan"])


def test_not_heard_for_the_stale_time_it_is_sent_stale_then_fresh_again(monkeypatch):
    r = robot()
    clock = [10.0]
    monkeypatch.setattr(diagnostics.time, "monotonic", lambda: clock[0])
    r.take(array(("battery", 1, "low", [])), TOPIC, lambda: None)
    r.due(clock[0], 5.0)
    clock[0] += 5.1
    sent, _, urgent = r.due(clock[0], 5.0)
    assert sent[0][1].stale and urgent and sent[0][1].level == 1
    assert r.due(clock[0] + 1, 5.0)[0] == []  # said once
    woken = []
    r.take(array(("battery", 1, "low", [])), TOPIC, lambda: woken.append(1))
    assert woken == [1] and not r.due(clock[0], 5.0)[0][0][1].stale


def test_text_values_and_statuses_are_bounded(monkeypatch):
    monkeypatch.setattr(protocol, "MAX_STATUSES", 2)
    r = robot()
    many = [("k", "v" * 1000)] * (protocol.MAX_STATUS_VALUES + 5)
    r.take(array(("a", 0, "m" * 1000, many), ("b", 9, "", []), ("c", 0, "", []), ("d", 0, "", [])), TOPIC,
           lambda: None)
    assert sorted(r.statuses) == ["a", "b"] and r.left_out == 2
    a = r.statuses["a"]
    assert len(a.message) == protocol.MAX_STATUS_MESSAGE and len(a.values) == protocol.MAX_STATUS_VALUES
    assert len(a.values[0][1]) == protocol.MAX_VALUE_TEXT
    assert r.statuses["b"].level == 2  # a level outside 0-3 counts as an error


def test_the_reporting_node_is_found_by_name_or_as_the_only_publisher():
    r = robot()
    r.publishers = {"/r1/diagnostics": ["/r1/lidar_driver", "/r1/battery_monitor"],
                    "/r1/diagnostics_agg": ["/r1/aggregator"]}
    assert r.publisher("lidar_driver: Scan rate", "/r1/diagnostics") == "/r1/lidar_driver"
    assert r.publisher("/R1/Sensors/lidar_driver: Scan rate", "/r1/diagnostics_agg") == "/r1/lidar_driver"
    assert r.publisher("Battery", "/r1/diagnostics") == ""  # two publish there: not known
    assert r.publisher("/R1/Sensors", "/r1/diagnostics_agg") == ""  # the aggregator's own summary
    r.publishers["/r1/diagnostics"] = ["/r1/battery_monitor"]
    assert r.publisher("Battery", "/r1/diagnostics") == "/r1/battery_monitor"


def test_facts_stay_well_under_what_the_site_reads():
    big = {"name": "n" * protocol.MAX_STATUS_NAME, "message": "m" * protocol.MAX_STATUS_MESSAGE,
           "values": [["k" * protocol.MAX_VALUE_KEY, "v" * protocol.MAX_VALUE_TEXT]] * protocol.MAX_STATUS_VALUES}
    split = diagnostics.parts([big] * 100)
    assert sum(len(p) for p in split) == 100 and len(split) > 1
    assert all(len(json.dumps(p)) < protocol.MAX_FACT_BYTES // 2 + 12_000 for p in split)
    assert [len(p) for p in diagnostics.parts([{"name": "x"}] * 250)] == [100, 100, 50]


def test_an_aggregated_status_belongs_to_the_node_of_the_status_with_its_hardware_id():
    r = robot()
    r.publishers = {"/r1/diagnostics": ["/r1/lidar_driver", "/r1/battery_monitor"],
                    "/r1/diagnostics_agg": ["/r1/aggregator"]}

    class Domain:
        class node:  # noqa: N801 - the graph as rclpy's node answers it
            @staticmethod
            def get_publishers_info_by_topic(topic):
                raise RuntimeError("the graph is not asked here")

    r.take(DiagnosticArray(status=[DiagnosticStatus(name="lidar_driver: Scan rate", hardware_id="sim_lidar"),
                                   DiagnosticStatus(name="Battery", hardware_id="bms")]), TOPIC, lambda: None)
    r.take(DiagnosticArray(status=[DiagnosticStatus(name="/R1/Sensors/Lidar", hardware_id="sim_lidar"),
                                   DiagnosticStatus(name="/R1/Power/Battery", hardware_id="bms")]),
           "/r1/diagnostics_agg", lambda: None)
    r.read_publishers(Domain)
    assert r.statuses["/R1/Sensors/Lidar"].node == "/r1/lidar_driver" and r.statuses["/R1/Sensors/Lidar"].changed
    assert r.statuses["/R1/Power/Battery"].node == ""  # its own status's node is not known either
