"""The test hosts of tests/integration/test_networks.py: the site's host (its Redis, reached from
the root namespace over one veth, and the site's ingest process), gateways and demo robots
started on hosts made of network namespaces (tests/netns.py), the waits that time discovery and
lost hosts, and the figures they record (written to tests/artifacts/networks.json)."""
from __future__ import annotations

import json
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from django.core.management import call_command

from lifecycle_site import local_redis
from lifecycle_site.fleet.models import Gateway, ManagedNode, Robot
from lifecycle_site.gateway_link import gateways as gateway_status
from tests import netns, stack

# Subnets of the layouts; the site's host has .254 on every LAN it is plugged into.
LAN, QUIET, SUBNET_A, SUBNET_B = "10.231.1.0/24", "10.231.2.0/24", "10.231.3.0/24", "10.231.4.0/24"
SITE_LEG = 254
UPLINK = "10.231.0.0/24"  # the site's host's /30 with the root namespace lies in it
DS_PORT = 11811
NODES = "lidar_driver,camera_driver"
ARTIFACT = stack.ROOT / "tests" / "artifacts" / "networks.json"
FIGURES: dict[str, float | None] = {}
GATEWAYS = ("net-lan", "net-quiet", "net-ds", "net-b")
LOST_WAIT = 30  # how long a test waits for a host's nodes to be shown lost (the bound is asserted apart)
BACK_WAIT = 30


def figure(name: str, seconds: float | None, waited: float = 0) -> float | None:
    """Record a measured time (None: it did not happen within ``waited`` seconds)."""
    FIGURES[name] = None if seconds is None else round(seconds, 2)
    print(f"[networks] {name}: " + (f"{seconds:.2f} s" if seconds is not None else f"not within {waited:g} s"))
    return seconds


@dataclass
class Site:
    """The site's host (Redis) and what the test process reaches it with."""

    fabric: netns.Fabric
    host: netns.Host
    redis_url: str
    redis_address: str
    tmp: Path
    gateways: dict[str, netns.NsProcess] = field(default_factory=dict)

    def attach(self, switch: netns.Switch, multicast: bool = True) -> str:
        """Plug the site's host into ``switch`` (no forwarding: it only answers for Redis)."""
        return self.fabric.plug(self.host, switch, SITE_LEG, multicast=multicast)

    def start_gateway(self, name: str, host: netns.Host, **dds: str) -> netns.NsProcess:
        """Register ``name`` (``manage.py add_gateway --redis-url`` the private address) and run
        ``python -m ros_gateway`` on ``host`` with the environment add_gateway wrote."""
        path = self.tmp / f"{name}.env"
        call_command("add_gateway", name, env_file=str(path), redis_url=self.redis_url)
        env = dict(line.split("=", 1) for line in path.read_text().splitlines() if "=" in line)
        assert f"@{self.redis_address}:" in env["REDIS_URL"], env["REDIS_URL"].split("@")[-1]
        process = host.start(name, [sys.executable, "-m", "ros_gateway", "--name", name],
                             stack.environment(DATABASE_URL=stack.GATEWAY_DATABASE_URL, **env, **dds))
        self.gateways[name] = process
        began = time.monotonic()
        stack.wait_for(lambda: gateway_status.status(name).online or not process.alive(), 60,
                       f"gateway {name} online")
        assert process.alive(), process.tail()
        figure(f"{name}: gateway start to online", time.monotonic() - began)
        return process


def launch(host: netns.Host, name: str, domain_id: int, nodes: str = NODES, namespace: str = "",
           **dds: str) -> netns.NsProcess:
    """Demo robot nodes on ``host`` with the DDS settings ``dds`` (not waiting for them)."""
    argv = [sys.executable, "-m", "ros_gateway.demo.robot", "--domain", str(domain_id), "--nodes", nodes]
    if namespace:
        argv += ["--namespace", namespace]
    return host.start(name, argv, stack.environment(**dds))


def ready(*processes: netns.NsProcess) -> float:
    """Wait until every robot process has its nodes up; returns when the last one had them."""
    at: dict[str, float] = {}

    def all_ready() -> bool:
        for process in processes:
            if process.name not in at and "demo robot ready" in process.output():
                at[process.name] = time.monotonic()
            assert process.alive(), process.tail()
        return len(at) == len(processes)

    stack.wait_for(all_ready, 30, f"robots {[p.name for p in processes]} ready")
    return max(at.values())


def discovered(node_keys: list[str], since: float, label: str) -> float:
    """Wait for the nodes alive at the site; record the time from ``since`` (robots ready)."""
    wait_alive(node_keys)
    return figure(label, time.monotonic() - since)


def keys(robot_name: str, nodes: str = NODES, prefix: str = "") -> list[str]:
    return [f"{robot_name}.{prefix}{n}" for n in nodes.split(",")]


def wait_alive(node_keys: list[str], alive: bool = True, timeout: float = 30) -> float:
    """Seconds until every node is (or none is) alive in the site's database."""
    began = time.monotonic()
    stack.wait_for(lambda: ManagedNode.objects.filter(key__in=node_keys, alive=alive).count() == len(node_keys),
                   timeout, f"{node_keys} alive={alive}", interval=0.05)
    return time.monotonic() - began


def measure(node_keys: list[str], alive: bool, timeout: float) -> float | None:
    """Like ``wait_alive``, but None when it does not happen within ``timeout``."""
    try:
        return wait_alive(node_keys, alive=alive, timeout=timeout)
    except AssertionError:
        return None


def pull_cable(host: netns.Host, node_keys: list[str], layout: str, wait_back: bool = True, hold: float = 0
               ) -> tuple[float | None, float | None]:
    """Pull the robot host's cable at the switch until its nodes are shown lost (or LOST_WAIT
    passed) and at least ``hold`` seconds, plug it back and (``wait_back``) wait for them to be
    alive again."""
    wait_alive(node_keys, timeout=10)
    host.cable(False)
    pulled = time.monotonic()
    try:
        lost = figure(f"{layout}: cable pulled to nodes shown not alive", measure(node_keys, False, LOST_WAIT),
                      LOST_WAIT)
        time.sleep(max(0.0, hold - (time.monotonic() - pulled)))
    finally:
        host.cable(True)
    back = None
    if wait_back:
        back = figure(f"{layout}: cable plugged back to nodes alive again", measure(node_keys, True, BACK_WAIT),
                      BACK_WAIT)
    return lost, back


@contextmanager
def site_host(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Site]:
    """The site's host: a namespace with the site's Redis, joined to the root namespace by one
    veth (the only thing the tests put there); the site's ingest process in the root
    namespace; this test process's Redis pointed at it. On the way out: the figures written,
    nothing of the namespaces left (asserted)."""
    request.config.add_cleanup(netns.close_all)  # the session's end, should the module not get there
    fabric = netns.Fabric("net")
    try:
        host = fabric.host("site")
        _, address = fabric.uplink(host)
        workdir = Path(stack.log_dir()).parent / "net-redis"
        workdir.mkdir(parents=True, exist_ok=True)
        redis_server = host.start("net-redis", [
            local_redis.server_binary(), "--bind", "0.0.0.0", "--port", "6379", "--protected-mode", "no",
            "--save", "", "--appendonly", "no", "--dir", str(workdir)], stack.environment())
        url = f"redis://{address}:6379/0"
        stack.wait_for(lambda: local_redis.answers(url), 15, f"Redis on {address} (the site's host)")
        ingest = netns.NsProcess(None, "net-ingest", [sys.executable, "manage.py", "ingest"],
                                 stack.environment(REDIS_URL=url), stack.log_dir())
        stack.wait_for(lambda: "ingest is running" in ingest.output() or not ingest.alive(), 30, "ingest")
        assert ingest.alive(), ingest.output()
        try:
            with stack.settings_redis(url):
                yield Site(fabric, host, url, address, tmp_path_factory.mktemp("networks"))
                for process in fabric.processes:
                    if process is not redis_server:
                        process.stop()
                Robot.objects.filter(gateway__name__in=GATEWAYS).delete()
                Gateway.objects.filter(name__in=GATEWAYS).delete()
        finally:
            ingest.stop()
    finally:
        fabric.close()
        if FIGURES:
            ARTIFACT.parent.mkdir(parents=True, exist_ok=True)
            ARTIFACT.write_text(json.dumps(FIGURES, indent=2) + "\n")
            print("[networks] figures written to", ARTIFACT)
    spaces, links = netns.ours()
    assert not spaces and not links, f"left behind: {spaces} {links}"
