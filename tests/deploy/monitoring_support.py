"""What tests/deploy/test_monitoring.py works with: the monitoring files and their queries, the
fleet it writes for the scrape, the gateway's beats, Prometheus's HTTP API, the variables
resolved as Grafana resolves them."""
from __future__ import annotations

import json
import re
import threading
import urllib.parse
import urllib.request
from datetime import timedelta
from pathlib import Path

import yaml

from tests import stack
from tests.deploy.engine import DOCKER_DIR, VERSION, DeployError, run

MONITORING_DIR = DOCKER_DIR / "monitoring"
OVERRIDE = MONITORING_DIR / "docker-compose.monitoring.yml"
PROMETHEUS_YML = MONITORING_DIR / "prometheus.yml"
DASHBOARD = MONITORING_DIR / "grafana" / "dashboards" / "lifecycle.json"
DATASOURCES = MONITORING_DIR / "grafana" / "provisioning" / "datasources" / "lifecycle-prometheus.yml"
PROVIDERS = MONITORING_DIR / "grafana" / "provisioning" / "dashboards" / "lifecycle.yml"
PROMETHEUS_IMAGE = f"lifecycle-prometheus:{VERSION}"
PROMETHEUS_UID = 10002  # the image's prometheus user (docker/monitoring/Dockerfile)
LABEL = "lifecycle.test=monitoring"  # on what this test makes in Docker (a killed run's leftovers go first)
SITE_TARGET = "web:8000"  # in prometheus.yml; here "web" is this host's address on the test's network

GATEWAY_ONLINE, GATEWAY_SILENT = "mon-gw-a", "mon-gw-b"
ROBOT_A, ROBOT_B = "mon-agv-1", "mon-agv-2"


def load_yaml(path: Path):
    return yaml.safe_load(path.read_text())


def dashboard() -> dict:
    return json.loads(DASHBOARD.read_text())


def query_panels(model: dict) -> list[dict]:
    """Every panel with queries (rows hold none; a collapsed row carries its panels inside)."""
    found = []
    for panel in model["panels"]:
        if panel["type"] == "row":
            found += panel.get("panels", [])
        else:
            found.append(panel)
    return found


# ---------------------------------------------------------------------------------------
# The Grafana files


def remove_leftovers() -> None:
    """Containers and networks a killed run of this test left (by label)."""
    containers = run(["docker", "ps", "-aq", "--filter", f"label={LABEL}"], timeout=30).stdout.split()
    if containers:
        run(["docker", "rm", "-f", *containers], timeout=60, check=False)
    for network in run(["docker", "network", "ls", "-q", "--filter", f"label={LABEL}"], timeout=30).stdout.split():
        run(["docker", "network", "rm", network], timeout=60, check=False)


def fleet() -> dict:
    """What the site's database holds for the scrape: every metric family gets series. Made as
    the unit tests make it (the ORM, in the test database the site process shares)."""
    from django.utils import timezone

    from lifecycle_site.alerts.models import Alert, Receiver, Rule
    from lifecycle_site.api.models import ApiToken
    from lifecycle_site.audit.models import TransitionRecord
    from lifecycle_site.diagnostics.models import ERROR, OK, WARN, Intake, Status
    from lifecycle_site.fleet.models import Gateway, ManagedNode, Robot
    from lifecycle_site.modes.models import CurrentMode, Mode
    from tests.conftest import make_user

    now = timezone.now()
    online = Gateway.objects.create(name=GATEWAY_ONLINE, backlog=3, logs_received=1200, logs_dropped=4, logs_lost=1,
                                    facts_lost=1, facts_rejected=2, redis_bytes=48_000)
    silent = Gateway.objects.create(name=GATEWAY_SILENT)  # never beat: offline
    robot_a = Robot.objects.create(name=ROBOT_A, domain_id=97, gateway=online)
    robot_b = Robot.objects.create(name=ROBOT_B, domain_id=98, gateway=silent)
    nodes = {}
    for robot, name, state, alive in (
            (robot_a, "/lidar_driver", "active", True), (robot_a, "/camera_driver", "active", True),
            (robot_a, "/planner", "inactive", True), (robot_a, "/flaky_node", "errorprocessing", True),
            (robot_a, "/old_driver", "unconfigured", False), (robot_b, "/arm", "unconfigured", True),
            (robot_b, "/gripper", "active", True)):
        nodes[robot.name, name] = ManagedNode.objects.create(robot=robot, name=name, state_label=state, alive=alive,
                                                             last_seen=now)

    def transitions(*attempts) -> None:
        node = nodes[ROBOT_A, "/lidar_driver"]
        for outcome, source, duration_ms in attempts:
            TransitionRecord.objects.create(
                node=node, robot=robot_a, robot_name=robot_a.name, node_name=node.name, transition_label="activate",
                outcome=outcome, source=source, requested_at=timezone.now() - timedelta(seconds=1),
                completed_at=timezone.now(), duration_ms=duration_ms)

    transitions(("succeeded", "api", 4.0), ("succeeded", "dashboard", 60.0), ("failed", "api", 900.0),
                ("timed_out", "cli", 5000.0), ("rejected", "api", None), ("observed", "external", None))
    production = Mode.objects.create(name="mon-production", nodes={"/lidar_driver": {"state": "active"},
                                                                   "/planner": {"state": "active"}},
                                     ready_when=[{"node": "/lidar_driver", "state": "active"}])
    maintenance = Mode.objects.create(name="mon-maintenance", nodes={"/arm": {"state": "inactive"}},
                                      ready_when=[{"node": "/arm", "state": "inactive"}])
    production.robots.add(robot_a)
    maintenance.robots.add(robot_b)
    CurrentMode.objects.create(robot=robot_a, mode=production, since=now)  # ready, one node drifts
    CurrentMode.objects.create(robot=robot_b, mode=maintenance, since=now)  # not ready
    receiver = Receiver.objects.create(name="mon-plant-webhook", url="http://127.0.0.1:9/hook", delivered=5, failed=1)
    rule = Rule.objects.create(name="mon-node-in-errorprocessing", kind=Rule.Kind.STATE, state="errorprocessing")
    rule.receivers.add(receiver)
    Rule.objects.create(name="mon-gateway-offline", kind=Rule.Kind.GATEWAY_OFFLINE)  # quiet: shows 0
    Alert.objects.create(rule=rule, rule_name=rule.name, subject=f"{ROBOT_A} /flaky_node", robot_name=ROBOT_A,
                         node_name="/flaky_node", summary="/flaky_node is in errorprocessing", since=now, fired_at=now)
    for robot, name, level, stale in ((robot_a, "lidar_driver: scan", OK, False),
                                      (robot_a, "camera_driver: frames", WARN, False),
                                      (robot_a, "battery: cell 3", ERROR, False),
                                      (robot_a, "imu: rate", OK, True), (robot_b, "arm: joints", OK, False)):
        Status.objects.create(robot=robot, name=name, level=level, stale=stale, message="test", heard=now,
                              level_since=now)
    Intake.objects.create(robot=robot_a, left_out_by_gateway=2, left_out_here=1)
    _, token = ApiToken.issue(make_user("mon-prometheus", "viewer"), "Prometheus scrape")
    return {"token": token, "transitions": transitions, "gateway": online}


def forget_fleet() -> None:
    from lifecycle_site.alerts.models import Alert, Receiver, Rule
    from lifecycle_site.fleet.models import Gateway, Robot
    from lifecycle_site.modes.models import Mode

    Alert.objects.filter(rule_name__startswith="mon-").delete()
    Rule.objects.filter(name__startswith="mon-").delete()
    Receiver.objects.filter(name__startswith="mon-").delete()
    Robot.objects.filter(name__in=(ROBOT_A, ROBOT_B)).delete()  # nodes, statuses, current modes with them
    Mode.objects.filter(name__startswith="mon-").delete()
    Gateway.objects.filter(name__in=(GATEWAY_ONLINE, GATEWAY_SILENT)).delete()


class Beats:
    """The gateway GATEWAY_ONLINE's heartbeat, written every half second as its process would."""

    def __init__(self) -> None:
        self.stopped = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stopped.is_set():
            stack.write_beat(GATEWAY_ONLINE)
            self.stopped.wait(0.5)

    def stop(self) -> None:
        self.stopped.set()
        self.thread.join(5)


class Prometheus:
    def __init__(self, port: int) -> None:
        self.base = f"http://127.0.0.1:{port}"

    def get(self, path: str, **params) -> dict:
        query = urllib.parse.urlencode(params, doseq=True)
        with urllib.request.urlopen(f"{self.base}{path}?{query}", timeout=10) as answer:
            body = json.loads(answer.read())
        assert body["status"] == "success", body
        return body["data"]

    def target(self) -> dict:
        (target,) = [t for t in self.get("/api/v1/targets")["activeTargets"]
                     if t["labels"]["job"] == "lifecycle-manager"]
        return target


def connects(address: str, port: int) -> bool:
    import socket

    with socket.socket() as probe:
        probe.settimeout(1)
        return probe.connect_ex((address, port)) == 0


def scraped(prometheus: Prometheus, after: str | None = None) -> dict | None:
    """The site's target once it is up and (``after``) scraped again since then."""
    target = prometheus.target()
    if target["health"] == "down":
        raise DeployError(f"Prometheus cannot scrape the site: {target['lastError']}")  # (retried until the bound)
    if target["health"] != "up" or (after is not None and target["lastScrape"] == after):
        return None
    return target


GRAFANA_BUILTINS = {"__rate_interval", "__interval", "__range"}


def variable_definition(variable: dict) -> str:
    query = variable["query"]
    return query["query"] if isinstance(query, dict) else query


def builtins(model: dict, scrape_interval_s: int) -> dict[str, str]:
    """Grafana's own variables as it would set them for the dashboard's default time range:
    $__rate_interval at least four scrape intervals (the data source's timeInterval)."""
    amount, unit = re.fullmatch(r"now-(\d+)([smhd])", model["time"]["from"]).groups()
    range_s = int(amount) * {"s": 1, "m": 60, "h": 3600, "d": 86400}[unit]
    return {"__rate_interval": f"{4 * scrape_interval_s}s", "__interval": f"{scrape_interval_s}s",
            "__range": f"{range_s}s"}


def substitute(expr: str, values: dict[str, str]) -> str:
    def one(match: re.Match) -> str:
        name = match.group(1) or match.group(2)
        assert name in values, f"no value for ${name} in {expr}"
        return values[name]

    return re.sub(r"\$\{(\w+)\}|\$(\w+)", one, expr)


def promql_regex_escape(value: str) -> str:
    """A label value inside a regex inside a PromQL string, as Grafana escapes it: regex
    metacharacters get a backslash, itself doubled for the string literal."""
    return re.sub(r"([\\^$.|?*+()\[\]{}])", r"\\\\\1", value)


def resolve_variables(prometheus: Prometheus, model: dict, values: dict[str, str]) -> dict[str, list[str]]:
    """Each variable's options as Grafana reads them (label_values(SELECTOR, LABEL): the label's
    values among the series SELECTOR matches, the variables before it substituted), and its
    value when all options are chosen, in Grafana's regex form for Prometheus: (a|b)."""
    options = {}
    for variable in model["templating"]["list"]:
        match = re.fullmatch(r"label_values\((?:(.+),\s*)?(\w+)\)", variable_definition(variable))
        selector, label = match.groups()
        params = {"match[]": substitute(selector, values)} if selector else {}
        found = prometheus.get(f"/api/v1/label/{label}/values", **params)
        assert found, f"${variable['name']}: {variable_definition(variable)} has no values"
        options[variable["name"]] = found
        values[variable["name"]] = "(" + "|".join(promql_regex_escape(v) for v in found) + ")"
    return options
