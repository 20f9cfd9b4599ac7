"""The demo robot's ROS 2 diagnostics on real rclpy: a robot process publishes the lidar's scan
rate, the battery and the flaky node's driver status on <namespace>/diagnostics at 1 Hz, the
statuses follow what happens (dropped points, a deactivated lidar, a failure_mode set through the
parameter service), and with --diagnostics-agg the robot's tree on diagnostics_agg has every parent
at the worst level of its children and a status not heard for 5 s as STALE. The aggregation and
the battery are also checked on their own, with made-up times."""
from __future__ import annotations

import sys
import threading
from typing import Any, Callable

import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
from rcl_interfaces.srv import SetParameters
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from ros_gateway.demo.diagnostics import (
    ERROR,
    OK,
    QOS,
    STALE,
    WARN,
    BatteryModel,
    BatteryMonitor,
    EventWindow,
    level_of,
)
from ros_gateway.demo.diagnostics_agg import Aggregate, DiagnosticAggregator, robot_name
from ros_gateway.demo.robot import parse_args
from tests import stack

DOMAIN_OFFSET = 44
NAMESPACE = "/agv1"
LIDAR, BATTERY, FLAKY = "lidar_driver: Scan rate", "battery_monitor: Battery", "flaky_node: Driver"
DIAG, AGG = "diagnostics", "diagnostics_agg"


def values(status: DiagnosticStatus) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


def expected_parent_level(levels: list[int]) -> int:
    """diagnostic_aggregator's rule, written out again: the worst child, stale counting as error
    unless every child is stale."""
    worst = max(levels)
    return ERROR if worst == STALE and any(level != STALE for level in levels) else worst


def check_parents(statuses: list[DiagnosticStatus]) -> None:
    """Every path with children is at the level its direct children call for."""
    levels = {s.name: level_of(s) for s in statuses}
    for name, level in levels.items():
        kids = [lv for child, lv in levels.items() if child.rpartition("/")[0] == name]
        if kids:
            assert level == expected_parent_level(kids), (name, level, kids)


class Listener:
    """The latest status per name on the robot's diagnostics and diagnostics_agg (and the latest
    whole aggregate), from an rclpy context of the test's own spun by a thread."""

    def __init__(self, domain_id: int) -> None:
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node("diagnostics_listener", context=self.context)
        self.latest: dict[str, dict[str, DiagnosticStatus]] = {DIAG: {}, AGG: {}}
        self.tree: list[DiagnosticStatus] = []
        self._lock = threading.Lock()
        for topic in (DIAG, AGG):
            self.node.create_subscription(
                DiagnosticArray, f"{NAMESPACE}/{topic}", lambda msg, topic=topic: self._on(topic, msg), QOS
            )
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def _on(self, topic: str, msg: DiagnosticArray) -> None:
        with self._lock:
            for status in msg.status:
                self.latest[topic][status.name] = status
            if topic == AGG:
                self.tree = list(msg.status)

    def status(self, topic: str, name: str) -> DiagnosticStatus | None:
        with self._lock:
            return self.latest[topic].get(name)

    def wait(self, topic: str, name: str, check: Callable[[DiagnosticStatus], None], timeout: float = 8.0):
        """The status once ``check`` (asserting) passes on it."""

        def passes() -> DiagnosticStatus | None:
            status = self.status(topic, name)
            assert status is not None, f"no {name!r} yet"
            check(status)
            return status

        return stack.wait_for(passes, timeout, f"{name!r} on {topic}", tolerate=(AssertionError,))

    def wait_tree(self, check: Callable[[dict[str, DiagnosticStatus]], None], timeout: float = 8.0):
        def passes() -> dict[str, DiagnosticStatus]:
            with self._lock:
                tree = {s.name: s for s in self.tree}
            assert tree, "no diagnostics_agg yet"
            check(tree)
            return tree

        return stack.wait_for(passes, timeout, "the aggregate", tolerate=(AssertionError,))

    def _call(self, future: Any, what: str) -> Any:
        stack.wait_for(future.done, 5.0, what)
        return future.result()

    def set_parameter(self, node: str, name: str, value: Any) -> None:
        """Through the node's real rcl_interfaces/srv/SetParameters service."""
        client = self.node.create_client(SetParameters, f"{NAMESPACE}/{node}/set_parameters")
        try:
            assert client.wait_for_service(timeout_sec=5.0), f"{node}/set_parameters"
            request = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
            answer = self._call(client.call_async(request), f"{node}.{name}:={value}")
            assert answer.results[0].successful, answer.results[0].reason
        finally:
            self.node.destroy_client(client)

    def transition(self, node: str, transition_id: int) -> None:
        client = self.node.create_client(ChangeState, f"{NAMESPACE}/{node}/change_state")
        try:
            assert client.wait_for_service(timeout_sec=5.0), f"{node}/change_state"
            request = ChangeState.Request(transition=Transition(id=transition_id))
            assert self._call(client.call_async(request), f"{node} transition {transition_id}").success
        finally:
            self.node.destroy_client(client)

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)
        self.thread.join(timeout=3.0)


@pytest.fixture
def robot(request):
    """Start a demo robot in /agv1 (lidar and flaky node, activated; a battery at 15 %, no dropped
    points) with the given extra arguments, and a listener; both end with the test, however it ends."""
    domain_id = stack.domain(DOMAIN_OFFSET)
    processes: list[stack.Process] = []
    listeners: list[Listener] = []

    def start(*extra: str) -> tuple[stack.Process, Listener]:
        argv = [sys.executable, "-m", "ros_gateway.demo.robot", "--domain", str(domain_id), "--namespace", NAMESPACE,
                "--nodes", "lidar_driver,flaky_node", "--param", "battery_monitor.initial_percent:=15.0",
                "--param", "lidar_driver.drop_probability:=0.0", "--autostart", "activate", *extra]
        process = stack.Process(f"diag-{request.node.name}", argv, stack.environment(), stack.log_dir())
        processes.append(process)  # before waiting: stopped even if it never gets ready
        stack.wait_for(lambda: "demo robot ready" in process.output() or not process.alive(), 20, "the robot")
        assert process.alive(), process.output()
        listeners.append(Listener(domain_id))
        return process, listeners[-1]

    try:
        yield start
    finally:
        for listener in listeners:
            listener.close()
        codes = [(process.stop(), process.output()) for process in processes]
        assert all(code == 0 for code, _ in codes), codes  # SIGTERM ends the robot cleanly


def test_lidar_battery_and_flaky_statuses_follow_the_robot(robot):
    process, ros = robot()
    # the ready line still names the demo nodes only
    ready = [line for line in process.output().splitlines() if line.startswith("demo robot ready:")]
    assert ready[-1] == "demo robot ready: /agv1/lidar_driver,/agv1/flaky_node"

    def scanning(s: DiagnosticStatus) -> None:
        v = values(s)
        assert (level_of(s), s.hardware_id, v["expected_hz"], v["dropped_points"]) == (OK, "sim_lidar_2d", "5.00", "0")
        assert 4.5 <= float(v["frequency_hz"]) <= 5.5 and s.message.startswith("scanning at"), (s.message, v)

    ros.wait(DIAG, LIDAR, scanning)

    def low(s: DiagnosticStatus) -> None:
        v = values(s)
        assert (level_of(s), s.message, s.hardware_id) == (WARN, "battery low, discharging", "sim_bms")
        assert 14.0 < float(v["percentage"]) <= 15.0 and 20.0 < float(v["voltage_v"]) < 30.0, v

    ros.wait(DIAG, BATTERY, low)
    flaky = ros.wait(DIAG, FLAKY, lambda s: None)
    assert (level_of(flaky), flaky.message, flaky.hardware_id) == (OK, "driver OK", "/dev/ttyFLAKY")
    assert values(flaky)["failure_mode"] == "none"
    assert ros.node.count_publishers(f"{NAMESPACE}/{AGG}") == 0  # no aggregator without --diagnostics-agg

    ros.set_parameter("battery_monitor", "initial_percent", 5.0)  # below the docking threshold: charging

    def critical(s: DiagnosticStatus) -> None:
        assert (level_of(s), s.message) == (ERROR, "battery critical, charging")
        assert values(s)["charging"] == "true" and 5.0 <= float(values(s)["percentage"]) < 10.0, values(s)

    ros.wait(DIAG, BATTERY, critical)

    ros.set_parameter("lidar_driver", "drop_probability", 1.0)  # every scan loses 3..18 points

    def dropping(s: DiagnosticStatus) -> None:
        assert level_of(s) == WARN and int(values(s)["dropped_points"]) > 10, (s.message, values(s))
        assert "points dropped in 5 s" in s.message, s.message

    ros.wait(DIAG, LIDAR, dropping)

    ros.transition("lidar_driver", Transition.TRANSITION_DEACTIVATE)

    def idle(s: DiagnosticStatus) -> None:
        assert (level_of(s), s.message) == (OK, "not active (inactive): not publishing scans")
        assert values(s)["frequency_hz"] == "0.00" and values(s)["state"] == "inactive"

    ros.wait(DIAG, LIDAR, idle)


def test_the_flaky_status_follows_failure_mode_from_warn_to_error(robot):
    _, ros = robot()
    ros.wait(DIAG, FLAKY, lambda s: None if level_of(s) == OK else _fail(s))
    ros.set_parameter("flaky_node", "failure_mode", "hang")  # takes effect at the next configure

    def warns(s: DiagnosticStatus) -> None:
        assert (level_of(s), s.message) == (WARN, "driver not answering (failure_mode=hang)")
        assert values(s)["failure_mode"] == "hang" and values(s)["state"] == "active", values(s)

    ros.wait(DIAG, FLAKY, warns, timeout=3.0)

    def errs(s: DiagnosticStatus) -> None:
        assert (level_of(s), s.message) == (ERROR, "driver not answering (failure_mode=hang)")
        assert float(values(s)["failing_for_s"]) >= 2.9, values(s)

    ros.wait(DIAG, FLAKY, errs, timeout=6.0)
    ros.set_parameter("flaky_node", "failure_mode", "none")
    ros.wait(DIAG, FLAKY, lambda s: None if (level_of(s), s.message) == (OK, "driver OK") else _fail(s), timeout=3.0)


def test_the_aggregate_has_parents_at_the_worst_child_and_a_silent_status_goes_stale(robot):
    _, ros = robot("--diagnostics-agg")
    paths = {"/AGV1", "/AGV1/Sensors", "/AGV1/Sensors/Lidar", "/AGV1/Power", "/AGV1/Power/Battery",
             "/AGV1/Drivers", "/AGV1/Drivers/Flaky node"}

    def healthy_but_low_battery(tree: dict[str, DiagnosticStatus]) -> None:
        assert set(tree) == paths, sorted(tree)
        levels = {name: level_of(s) for name, s in tree.items()}
        assert levels["/AGV1/Sensors/Lidar"] == OK, tree["/AGV1/Sensors/Lidar"].message
        assert levels == {**dict.fromkeys(paths, OK), "/AGV1/Power/Battery": WARN, "/AGV1/Power": WARN,
                          "/AGV1": WARN}, levels
        assert tree["/AGV1/Power"].message == "warning: Battery"
        assert values(tree["/AGV1/Power"]) == {"Battery": "battery low, discharging"}
        assert tree["/AGV1/Sensors/Lidar"].hardware_id == "sim_lidar_2d"
        assert "frequency_hz" in values(tree["/AGV1/Sensors/Lidar"])
        check_parents(list(tree.values()))

    ros.wait_tree(healthy_but_low_battery)
    # a finalized node says nothing any more (as if it were gone): its status goes stale after 5 s
    ros.transition("flaky_node", Transition.TRANSITION_ACTIVE_SHUTDOWN)

    def flaky_stale(tree: dict[str, DiagnosticStatus]) -> None:
        flaky = tree["/AGV1/Drivers/Flaky node"]
        assert (level_of(flaky), flaky.message) == (STALE, "stale"), flaky.message
        assert values(flaky)["failure_mode"] == "none"  # the last values are kept
        assert level_of(tree["/AGV1/Drivers"]) == STALE  # all its children are stale
        assert (level_of(tree["/AGV1"]), tree["/AGV1"].message) == (ERROR, "error: Drivers")
        check_parents(list(tree.values()))

    ros.wait_tree(flaky_stale, timeout=10.0)


# -- the parts on their own ----------------------------------------------------------------------
def status(name: str, level: int, message: str = "") -> DiagnosticStatus:
    return DiagnosticStatus(name=name, level=bytes([level]), message=message or f"level {level}",
                            values=[KeyValue(key="k", value="v")])


def test_aggregate_tree_levels_and_staleness_with_made_up_times():
    aggregate = Aggregate("AGV2", stale_after_s=5.0)
    assert [(s.name, level_of(s)) for s in aggregate.report(0.0)] == [("/AGV2", STALE)]
    aggregate.add(status("lidar_driver: Scan rate", OK), 0.0)
    aggregate.add(status("lidar_driver: Motor", WARN), 0.0)  # two statuses of one component: a leaf each
    aggregate.add(status("camera_driver: Frames", OK), 3.0)
    aggregate.add(status("battery_monitor: Battery", OK), 3.0)
    aggregate.add(status("odometry", ERROR), 3.0)  # not "<node>: <task>", matching no rule
    report = {s.name: s for s in aggregate.report(4.0)}
    assert {name: level_of(s) for name, s in report.items()} == {
        "/AGV2": ERROR, "/AGV2/Other": ERROR, "/AGV2/Other/odometry": ERROR,
        "/AGV2/Power": OK, "/AGV2/Power/Battery": OK,
        "/AGV2/Sensors": WARN, "/AGV2/Sensors/Camera": OK,
        "/AGV2/Sensors/Lidar": WARN, "/AGV2/Sensors/Lidar/Motor": WARN, "/AGV2/Sensors/Lidar/Scan rate": OK,
    }
    assert report["/AGV2/Sensors"].message == "warning: Lidar"
    assert values(report["/AGV2/Sensors/Lidar/Motor"]) == {"k": "v"}
    # 6 s later the lidar's two statuses are stale, the camera's not yet
    report = {s.name: s for s in aggregate.report(6.0)}
    assert (level_of(report["/AGV2/Sensors/Lidar/Scan rate"]), report["/AGV2/Sensors/Lidar/Scan rate"].message) == (
        STALE, "stale")
    assert level_of(report["/AGV2/Sensors/Lidar"]) == STALE  # all children stale
    assert level_of(report["/AGV2/Sensors"]) == ERROR  # one stale child among fresh ones is an error
    check_parents(list(report.values()))
    aggregate.add(status("lidar_driver: Scan rate", OK), 6.5)
    report = {s.name: level_of(s) for s in aggregate.report(7.0)}
    assert report["/AGV2/Sensors/Lidar/Scan rate"] == OK and report["/AGV2/Sensors/Lidar"] == ERROR
    assert (robot_name("/agv1"), robot_name("/site/agv_2"), robot_name(""), robot_name("/")) == (
        "AGV1", "AGV_2", "Robot", "Robot")


def test_battery_drains_docks_late_and_recharges_in_a_loop():
    battery = BatteryModel(25.0)
    seen: list[tuple[int, bool]] = []
    for _ in range(2 * 60 * 60):  # two hours, a second at a time, at 2 %/min down and 10 %/min up
        battery.step(1.0, 2.0, 10.0)
        level, message, v = battery.report()
        assert level == (ERROR if battery.percent < 10 else WARN if battery.percent < 20 else OK), battery.percent
        assert message.endswith("charging" if battery.charging else "discharging")
        assert 21.0 <= v["voltage_v"] <= 29.8 and 0.0 <= v["percentage"] <= 100.0
        if not seen or seen[-1] != (level, battery.charging):
            seen.append((level, battery.charging))
    # discharging through WARN and ERROR, charging back through ERROR and WARN to OK, again
    cycle = [(OK, False), (WARN, False), (ERROR, False), (ERROR, True), (WARN, True), (OK, True)]
    assert seen[:8] == [(OK, False), *cycle[1:], (OK, False), (WARN, False)]
    assert all(step in cycle for step in seen)


def test_event_window_frequency_is_read_from_the_intervals():
    window = EventWindow(window_s=5.0)
    assert window.frequency(now=window.since) == 0.0
    start = window.since
    for i in range(1, 6):  # 5 Hz for one second only: 5 Hz, not 1 s worth of a 5 s window
        window.add(now=start + 0.2 * i)
    assert window.frequency(now=start + 1.05) == pytest.approx(5.0)
    window.add(amount=7, now=start + 1.1)
    assert window.total(now=start + 1.2) == 12  # five events of 1 and one of 7
    assert window.total(now=start + 7.0) == 0 and window.last(now=start + 7.0) is None


def test_the_robot_options_choose_its_helper_nodes():
    opts, _ = parse_args(["--nodes", "lidar_driver", "--param", "battery_monitor.initial_percent:=50"])
    assert opts.helper_classes == [BatteryMonitor] and not opts.diagnostics_agg
    opts, _ = parse_args(["--nodes", "lidar_driver", "--diagnostics-agg", "--no-battery"])
    assert opts.helper_classes == [DiagnosticAggregator]
    with pytest.raises(SystemExit):  # no battery node to take the parameter
        parse_args(["--nodes", "lidar_driver", "--no-battery", "--param", "battery_monitor.initial_percent:=50"])


def _fail(status: DiagnosticStatus) -> None:
    raise AssertionError(f"level {level_of(status)}: {status.message!r}")
