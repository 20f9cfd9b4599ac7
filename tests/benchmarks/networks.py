"""Scenario 9: robots where they are, on test hosts made of network namespaces (tests/netns.py).

Side by side in one run, one layout after another:

1. discovery of 100 lifecycle nodes on two remote robot hosts (50 per host, one demo robot
   process each), from "robot processes ready" to "the site's API lists all of them alive",
   for (a) one LAN with multicast (``SUBNET``), (b) one LAN whose switch drops multicast
   (static peers both ways), (c) robots behind a router with a Fast DDS discovery server (the
   gateway a super client); the 1-minute load average beside each;
2. API transitions (configure, cleanup) to a node on a remote host (LAN) against a node of a
   robot process in the gateway's own namespace;
3. the liveness probe's cost: the gateway's CPU at rest with LIFECYCLE_LIVENESS_INTERVAL=1 and 0
   (the same gateway restarted, LAN layout), and its probe calls per second.

The site (ingest, daphne) runs in the root namespace with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST;
its Redis in the site's host namespace, reached over the fabric's one private veth. Everything
in the namespaces is removed at the end, also on failure (the Fabric context manager).
Needs root (``ip netns``, ``ebtables``).
"""
from __future__ import annotations

import json
import os
import sys
import sysconfig
import time
from pathlib import Path

from tests import domains, netns
from tests.benchmarks.harness import GATEWAY_DATABASE_URL, BenchContext
from tests.benchmarks.processes import PYTHON, BenchError, Child, environment, read_env_file, run_manage, wait_for
from tests.benchmarks.report import ScenarioResult
from tests.benchmarks.system import cpu_seconds, free_port, loadavg
from tests.benchmarks.web import Http

NAME = "networks"
TITLE = "9. Robots where they are: discovery per network layout, remote vs local transition, liveness cost"
LAN, QUIET, SUBNET_A, SUBNET_B = "10.231.1.0/24", "10.231.2.0/24", "10.231.3.0/24", "10.231.4.0/24"
UPLINK = "10.231.0.0/24"
SITE_LEG = 254
DS_PORT = 11811
# The other scenarios use 120-126. Each layout's DDS stays on its own switch, so the layouts
# (one after another) share the two robots' domains.
DOMAINS = {"a": (127, 128), "b": (127, 128), "c": (127, 128)}
LOCAL_DOMAIN = 129
PREFIX = "bench_node"
DISCOVERY_TIMEOUT_S = 120.0


class Sizes:
    def __init__(self, quick: bool) -> None:
        self.per_host = 10 if quick else 50
        self.transitions = 10 if quick else 25  # configure + cleanup pairs per node
        self.rest_s = 5.0 if quick else 20.0


class NetSite:
    """The site: Redis in the site's host namespace; ingest and daphne in the root namespace."""

    def __init__(self, ctx: BenchContext, fabric: netns.Fabric) -> None:
        from lifecycle_site import local_redis

        self.fabric = fabric
        self.dir = ctx.workdir / NAME
        ctx.template.copy_to(self.dir)
        self.log_dir = self.dir / "logs"
        self.log_dir.mkdir()
        self.host = fabric.host("site")
        _, address = fabric.uplink(self.host)
        self.redis_url = f"redis://{address}:6379/0"
        (self.dir / "redis").mkdir()
        self.host.start("redis", [local_redis.server_binary(), "--bind", "0.0.0.0", "--port", "6379",
                                  "--protected-mode", "no", "--save", "", "--appendonly", "no",
                                  "--dir", str(self.dir / "redis")], environment(self.dir, 6379), self.log_dir)
        wait_for(lambda: local_redis.answers(self.redis_url), 15, "Redis on the site's host")
        self.env = environment(self.dir, 6379, REDIS_URL=self.redis_url)
        self.children: list[Child] = []
        self.gateways: dict[str, netns.NsProcess] = {}
        port = free_port()
        self.ingest = self._spawn("ingest", [PYTHON, "manage.py", "ingest"])
        self.site = self._spawn("daphne", [PYTHON, "-m", "lifecycle_site.serve", "-b", "127.0.0.1", "-p", str(port),
                                           "lifecycle_site.asgi:application"])
        self.api = Http("127.0.0.1", port, token=ctx.template.token)
        wait_for(lambda: "holding the ingest lease" in self.ingest.output() or not self.ingest.alive(), 60,
                 "the ingest process to take its lease")
        wait_for(lambda: self._answers() or not self.site.alive(), 30, "daphne to listen")
        for child in self.children:
            if not child.alive():
                raise BenchError(f"{child.name} exited on start:\n{child.output()[-3000:]}")

    def _spawn(self, name: str, argv: list[str]) -> Child:
        child = Child(name, argv, self.env, self.log_dir)
        self.children.append(child)
        return child

    def _answers(self) -> bool:
        try:
            return self.api.get("/api/v1/robots").status == 200
        except OSError:
            return False

    def stop(self) -> None:
        for child in reversed(self.children):
            child.stop()

    def attach(self, switch: netns.Switch, multicast: bool = True) -> str:
        return self.fabric.plug(self.host, switch, SITE_LEG, multicast=multicast)

    def register(self, gateway: str, robots: list[tuple[str, int]]) -> None:
        env_file = self.dir / f"{gateway}.env"
        run_manage(self.env, "add_gateway", gateway, "--env-file", str(env_file), "--redis-url", self.redis_url)
        for robot, domain in robots:
            run_manage(self.env, "add_robot", robot, "--domain", str(domain), "--gateway", gateway)

    def start_gateway(self, gateway: str, host: netns.Host, **dds: str) -> netns.NsProcess:
        """``gateway`` (registered) on ``host``: the benchmark's wrapper of the product's gateway,
        which writes its counters to <dir>/<gateway>-stats.json."""
        env = dict(self.env, DATABASE_URL=GATEWAY_DATABASE_URL, **read_env_file(self.dir / f"{gateway}.env"), **dds)
        stats = self.dir / f"{gateway}-stats.json"
        process = host.start(gateway, [PYTHON, "-m", "tests.benchmarks.gateway_main", gateway, str(stats)], env,
                             self.log_dir)
        self.gateways[gateway] = process

        def online() -> bool:
            listed = {g["name"]: g for g in self.api.get("/api/v1/gateways").json()["gateways"]}
            return bool(listed.get(gateway, {}).get("online")) or not process.alive()

        wait_for(online, 60, f"gateway {gateway} online", 0.25)
        if not process.alive():
            raise BenchError(f"gateway {gateway} exited:\n{process.tail()}")
        return process

    def gateway_stats(self, gateway: str) -> dict:
        try:
            return json.loads((self.dir / f"{gateway}-stats.json").read_text())
        except (OSError, ValueError):
            return {}

    def robot(self, host: netns.Host, name: str, domain: int, count: int, **dds: str) -> netns.NsProcess:
        argv = [PYTHON, "-m", "ros_gateway.demo.robot", "--domain", str(domain), "--nodes", "", "--generic",
                str(count), "--generic-prefix", PREFIX, "--ros-args", "--disable-external-lib-logs"]
        return host.start(name, argv, environment(self.dir, 6379, **dds), self.log_dir)

    def alive(self, keys: set[str]) -> bool:
        response = self.api.get("/api/v1/nodes")
        if response.status != 200:
            return False
        return keys <= {n["id"] for n in response.json()["nodes"] if n["alive"]}


def node_keys(robot: str, count: int) -> set[str]:
    return {f"{robot}.{PREFIX}_{i:03d}" for i in range(count)}


def ready(processes: list[netns.NsProcess], timeout: float = 90) -> float:
    at: dict[str, float] = {}

    def all_ready() -> bool:
        for process in processes:
            if process.name not in at and "demo robot ready" in process.output():
                at[process.name] = time.monotonic()
            if not process.alive():
                raise BenchError(f"robot process died:\n{process.tail()}")
        return len(at) == len(processes)

    wait_for(all_ready, timeout, "robot processes ready", 0.05)
    return max(at.values())


def discover(site: NetSite, label: str, robots: list[netns.NsProcess], keys: set[str],
             result: ScenarioResult) -> None:
    since = ready(robots)
    wait_for(lambda: site.alive(keys), DISCOVERY_TIMEOUT_S, f"{len(keys)} nodes alive ({label})", 0.1)
    result.figure(f"{label}: {len(keys)} nodes, robots ready to all alive", time.monotonic() - since, "s")
    result.figure(f"{label}: 1-min load average", loadavg()[0], "")


def lan_hosts(site: NetSite, switch_name: str, subnet: str, multicast: bool, tag: str) -> list[netns.Host]:
    switch = site.fabric.switch(switch_name, subnet)
    leg = site.attach(switch, multicast=multicast)
    hosts = [site.fabric.host(f"{tag}-{h}") for h in ("gw", "r1", "r2")]
    for octet, host in zip((10, 11, 12), hosts, strict=True):
        site.fabric.plug(host, switch, octet, multicast=multicast)
        host.route(UPLINK, leg)
    if not multicast:
        switch.drop_multicast()
    return hosts


def transitions(site: NetSite, keys: dict[str, str], pairs: int, result: ScenarioResult) -> None:
    """configure + cleanup through the API, interleaved between the nodes."""
    series = {where: result.new_series(f"API transition, node on {where}") for where in keys}
    for _ in range(pairs):
        for where, key in keys.items():
            for label in ("configure", "cleanup"):
                response = site.api.transition(key, label)
                if response.status != 200:
                    raise BenchError(f"API {label} on {key} answered {response.status}: {response.body[:300]!r}")
                series[where].add(response.ms)
                time.sleep(0.08)


def rest_cpu(site: NetSite, gateway: str, process: netns.NsProcess, seconds: float, label: str,
             result: ScenarioResult) -> None:
    before_cpu, before_probes = cpu_seconds(process.popen.pid), site.gateway_stats(gateway).get("liveness_probes", 0)
    began = time.monotonic()
    time.sleep(seconds)
    elapsed = time.monotonic() - began
    share = (cpu_seconds(process.popen.pid) - before_cpu) / elapsed * 100
    probes = (site.gateway_stats(gateway).get("liveness_probes", 0) - before_probes) / elapsed
    result.figure(f"gateway CPU at rest, {label}", share, "% of a core")
    result.figure(f"liveness probe calls, {label}", probes, "per s")


def layout_lan(site: NetSite, sizes: Sizes, result: ScenarioResult) -> None:
    """(a) LAN with multicast, then on it: remote vs local transitions, liveness on vs off."""
    gw, r1, r2 = lan_hosts(site, "lan", LAN, True, "a")
    dds = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}
    robots = [("bench-a1", DOMAINS["a"][0]), ("bench-a2", DOMAINS["a"][1])]
    site.register("bench-lan", [*robots, ("bench-local", LOCAL_DOMAIN)])
    gateway = site.start_gateway("bench-lan", gw, **dds)
    processes = [site.robot(host, name, domain, sizes.per_host, **dds)
                 for host, (name, domain) in zip((r1, r2), robots, strict=True)]
    keys = node_keys("bench-a1", sizes.per_host) | node_keys("bench-a2", sizes.per_host)
    discover(site, "(a) LAN, multicast (SUBNET)", processes, keys, result)

    local = site.robot(gw, "bench-local", LOCAL_DOMAIN, 1, **dds)
    ready([local])
    keys |= node_keys("bench-local", 1)
    wait_for(lambda: site.alive(keys), 60, "the local robot's node alive", 0.1)
    transitions(site, {"a remote host (LAN)": f"bench-a1.{PREFIX}_000",
                       "the gateway's own host": f"bench-local.{PREFIX}_000"}, sizes.transitions, result)

    total = len(keys)
    time.sleep(3.0)  # the transitions' follow-up work settles
    rest_cpu(site, "bench-lan", gateway, sizes.rest_s, f"{total} nodes in 3 processes, liveness interval 1 s",
             result)
    gateway.stop()
    gateway = site.start_gateway("bench-lan", gw, LIFECYCLE_LIVENESS_INTERVAL="0", **dds)
    wait_for(lambda: site.alive(keys), 60, "the nodes alive again (gateway restarted)", 0.1)
    time.sleep(3.0)
    rest_cpu(site, "bench-lan", gateway, sizes.rest_s, f"{total} nodes in 3 processes, liveness off (0)", result)
    for process in [gateway, local, *processes]:
        process.stop()


def layout_quiet(site: NetSite, sizes: Sizes, result: ScenarioResult) -> None:
    """(b) LAN whose switch drops multicast: static peers both ways."""
    gw, r1, r2 = lan_hosts(site, "quiet", QUIET, False, "b")
    robots = [("bench-b1", DOMAINS["b"][0]), ("bench-b2", DOMAINS["b"][1])]
    site.register("bench-quiet", robots)
    gateway = site.start_gateway("bench-quiet", gw, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                                 ROS_STATIC_PEERS=f"{r1.address};{r2.address}")
    processes = [site.robot(host, name, domain, sizes.per_host, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                            ROS_STATIC_PEERS=gw.address)
                 for host, (name, domain) in zip((r1, r2), robots, strict=True)]
    keys = node_keys("bench-b1", sizes.per_host) | node_keys("bench-b2", sizes.per_host)
    discover(site, "(b) LAN, no multicast (static peers)", processes, keys, result)
    for process in [gateway, *processes]:
        process.stop()


def layout_routed(site: NetSite, sizes: Sizes, result: ScenarioResult) -> None:
    """(c) robots in subnet B behind a router running a Fast DDS discovery server."""
    fabric = site.fabric
    a, b = fabric.switch("sub-a", SUBNET_A), fabric.switch("sub-b", SUBNET_B)
    leg = site.attach(a)
    router = fabric.router("router")
    router_a, router_b = fabric.plug(router, a, 1), fabric.plug(router, b, 1)
    router.route(UPLINK, leg)
    gw = fabric.host("c-gw")
    fabric.plug(gw, a, 10)
    gw.route(UPLINK, leg)
    gw.route(SUBNET_B, router_a)
    hosts = [fabric.host("c-r1"), fabric.host("c-r2")]
    for octet, host in zip((21, 22), hosts, strict=True):
        fabric.plug(host, b, octet)
        host.route(SUBNET_A, router_b)
    libs = f"{sys.prefix}/lib:{sysconfig.get_paths()['purelib']}/ros_fastrtps.libs"
    server = router.start("discovery-server", [str(Path(PYTHON).parent / "fast-discovery-server"), "-i", "0",
                                               "-l", "0.0.0.0", "-p", str(DS_PORT)],
                          dict(os.environ, LD_LIBRARY_PATH=libs), site.log_dir)
    wait_for(lambda: "Server GUID prefix" in server.output() or not server.alive(), 15, "the discovery server")
    if not server.alive():
        raise BenchError(f"the discovery server exited:\n{server.tail()}")
    robots = [("bench-c1", DOMAINS["c"][0]), ("bench-c2", DOMAINS["c"][1])]
    site.register("bench-routed", robots)
    gateway = site.start_gateway("bench-routed", gw, ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET",
                                 ROS_DISCOVERY_SERVER=f"{router_a}:{DS_PORT}", ROS_SUPER_CLIENT="TRUE")
    processes = [site.robot(host, name, domain, sizes.per_host, ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET",
                            ROS_DISCOVERY_SERVER=f"{router_b}:{DS_PORT}")
                 for host, (name, domain) in zip(hosts, robots, strict=True)]
    keys = node_keys("bench-c1", sizes.per_host) | node_keys("bench-c2", sizes.per_host)
    discover(site, "(c) routed, discovery server", processes, keys, result)
    for process in [gateway, *processes, server]:
        process.stop()


def run(ctx: BenchContext) -> ScenarioResult:
    result = ScenarioResult(NAME, TITLE, load_before=loadavg())
    if os.geteuid() != 0:
        result.notes.append("skipped: needs root (ip netns, ebtables)")
        return result
    sizes = Sizes(ctx.quick)
    claimed = sorted({*DOMAINS["a"], *DOMAINS["b"], *DOMAINS["c"], LOCAL_DOMAIN})
    try:
        domains.claim(claimed)
    except domains.DomainInUse as exc:
        raise BenchError(f"{exc}: wait for the other benchmark run to end") from None
    result.notes.append(f"2 robot hosts x {sizes.per_host} nodes (one demo robot process each) per layout; "
                        "gateway, robots, Redis in network namespaces; ingest and daphne in the root namespace")
    try:
        with netns.Fabric("nb") as fabric:
            site = NetSite(ctx, fabric)
            try:
                layout_lan(site, sizes, result)
                layout_quiet(site, sizes, result)
                layout_routed(site, sizes, result)
            finally:
                site.stop()
    finally:
        domains.release(claimed)
    return result
