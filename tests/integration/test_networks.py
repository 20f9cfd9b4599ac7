"""Robots where they are: the real site, gateways and demo robots on test hosts made of network
namespaces (tests/netns.py): one LAN with multicast, one without, and two subnets behind a
router (a Fast DDS discovery server; a gateway of its own in the robots' subnet).

The site (this test process and its ingest process) stays in the root namespace with
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST; its Redis runs in the namespace of the site's host,
which the root namespace reaches over one private veth and the gateways over routes. No DDS
and no multicast reach the root namespace (the last test checks its link's counters).

Figures (time to find the nodes, to see a lost host, ...) are printed as ``[networks] ...``
(with ``-s``) and written to tests/artifacts/networks.json; docs/networks.md quotes them.
"""
from __future__ import annotations

import signal
import sys
import sysconfig
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from lifecycle_site.audit.models import ParameterRecord, TransitionRecord
from lifecycle_site.fleet.models import LogRecord, ManagedNode, Robot
from tests import netns, stack
from tests.integration.conftest import register, transition, wait_node
from tests.integration.networks import (
    BACK_WAIT,
    DS_PORT,
    LAN,
    LOST_WAIT,
    QUIET,
    SUBNET_A,
    SUBNET_B,
    UPLINK,
    Site,
    discovered,
    figure,
    keys,
    launch,
    pull_cable,
    ready,
    site_host,
)


@pytest.fixture(autouse=True)
def show_logs_on_failure(request, site):
    """The tails of the gateways' logs (and of any process that ended) under a failing test's report."""
    failed = request.session.testsfailed
    yield
    if request.session.testsfailed > failed:
        shown = [p for p in site.fabric.processes if p in site.gateways.values() or not p.alive()]
        print("\n".join(p.tail(30) for p in shown))


@pytest.fixture(scope="module")
def site(live_db, request, tmp_path_factory):
    """The site's host (networks.site_host), once for all the layouts of this module."""
    with site_host(request, tmp_path_factory) as site:
        yield site


# -- 1 and 4: one LAN, discovery by multicast (ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET) -------------

@dataclass
class Lan:
    site: Site
    gateway: netns.NsProcess
    hosts: dict[str, netns.Host]
    robots: dict[str, netns.NsProcess]


@pytest.fixture(scope="module")
def lan(site):
    """Switch ``lan``: the gateway's host and two robot hosts (and the site's host for Redis)."""
    fabric = site.fabric
    switch = fabric.switch("lan", LAN)
    site_leg = site.attach(switch)
    hosts = {name: fabric.host(name) for name in ("lan-gw", "lan-r1", "lan-r2")}
    for octet, host in zip((10, 11, 12), hosts.values(), strict=True):
        fabric.plug(host, switch, octet)
        host.route(UPLINK, site_leg)
    assert netns.udp_probe(hosts["lan-r1"], hosts["lan-gw"]) == {"multicast": True, "unicast": True}
    register("lan-r1", stack.domain(13), gateway="net-lan")
    register("lan-r2", stack.domain(14), gateway="net-lan")
    gateway = site.start_gateway("net-lan", hosts["lan-gw"], ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET")
    robots = {
        "lan-r1": launch(hosts["lan-r1"], "lan-r1-nodes", stack.domain(13), ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET"),
        "lan-r2": launch(hosts["lan-r2"], "lan-r2-nodes", stack.domain(14), "lidar_driver,planner",
                         ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET"),
    }
    discovered(keys("lan-r1") + keys("lan-r2", "lidar_driver,planner"), ready(*robots.values()),
               "LAN (multicast, SUBNET): robots ready to 4 nodes on 2 hosts alive at the site")
    yield Lan(site, gateway, hosts, robots)
    for process in robots.values():
        process.stop()


def test_lan_robots_found_and_operated_through_the_site(api, lan):
    # A transition through the site's API, carried out over the LAN.
    response = transition(api, "lan-r1.lidar_driver", "configure")
    assert response.status_code == 200, response.json()
    record = TransitionRecord.objects.get(id=response.json()["record_id"])
    assert (record.robot_name, record.outcome, record.requested_by_name) == ("lan-r1", "succeeded", "ivan-operator")
    assert ManagedNode.objects.get(key="lan-r1.lidar_driver").state_label == "inactive"

    # Parameters: read and set.
    key = "lan-r2.lidar_driver"
    listed = {p["name"]: p for p in api.get(f"/api/v1/nodes/{key}/parameters").json()["parameters"]}
    assert listed["scan_rate_hz"]["type"] == "double", listed["scan_rate_hz"]
    response = api.patch(f"/api/v1/nodes/{key}/parameters", {"scan_rate_hz": 7.0}, content_type="application/json")
    assert response.status_code == 200, response.json()
    listed = {p["name"]: p["value"] for p in api.get(f"/api/v1/nodes/{key}/parameters").json()["parameters"]}
    assert listed["scan_rate_hz"] == 7.0
    assert ParameterRecord.objects.filter(node__key=key, name="scan_rate_hz", outcome="succeeded").exists()

    # Log lines from /rosout on the robot's host, stored by the site's ingest process.
    stack.wait_for(lambda: LogRecord.objects.filter(node__key="lan-r1.lidar_driver").exists(), 15,
                   "log lines of lan-r1.lidar_driver stored")
    records = api.get("/api/v1/nodes/lan-r1.lidar_driver/logs").json()["records"]
    assert records, "no log lines through the API"

    # A group run on the other host.
    response = api.post("/api/v1/robots/lan-r2/operations?wait=30", {"operation": "bringup"},
                        content_type="application/json")
    run = response.json()["run"]
    assert run["status"] == "succeeded", run
    assert {r["state"]["label"] for r in run["results"]} == {"active"}


def test_lan_recovery_after_the_robot_process_is_killed(api, lan):
    """lan-r1's camera_driver should be active: after a crash of the robot's process (its
    supervisor restarts it) the gateway brings it back."""
    Robot.objects.filter(name="lan-r1").update(auto_recover=True)
    key = "lan-r1.camera_driver"
    for name in ("configure", "activate"):
        assert transition(api, key, name).status_code == 200
    response = api.put(f"/api/v1/nodes/{key}/desired-state", {"desired_state": "active"},
                       content_type="application/json")
    assert response.status_code == 200, response.json()
    host = lan.hosts["lan-r1"]
    lan.robots["lan-r1"].stop(signal.SIGKILL)
    lan.robots["lan-r1"] = launch(host, "lan-r1-nodes-2", stack.domain(13), ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET")
    began = ready(lan.robots["lan-r1"])
    record = stack.wait_for(
        lambda: TransitionRecord.objects.filter(node__key=key, source="recovery", transition_label="activate",
                                                outcome="succeeded").first(),
        30, "the recovery to bring lan-r1.camera_driver back to active")
    assert record.run_id
    wait_node(None, key, alive=True, state="active", timeout=10)
    figure("LAN: robot restarted (ready) to node recovered (active again)", time.monotonic() - began)


def test_robots_on_one_domain_are_told_apart_by_namespace(api, lan):
    domain_id = stack.domain(15)
    register("ns-left", domain_id, namespace="/left", gateway="net-lan")
    register("ns-right", domain_id, namespace="/right", gateway="net-lan")
    processes = [
        launch(lan.hosts["lan-r1"], "ns-left-nodes", domain_id, namespace="/left",
               ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET"),
        launch(lan.hosts["lan-r2"], "ns-right-nodes", domain_id, namespace="/right",
               ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET"),
    ]
    try:
        discovered(keys("ns-left", prefix="left.") + keys("ns-right", prefix="right."), ready(*processes),
                   "LAN: 2 robots on one domain (namespaces), ready to 4 nodes alive")
        for name, prefix in (("ns-left", "left."), ("ns-right", "right.")):
            listed = api.get(f"/api/v1/nodes?robot={name}").json()["nodes"]
            assert sorted(n["id"] for n in listed) == sorted(keys(name, prefix=prefix)), listed
            assert {n["name"] for n in listed} == {f"/{prefix[:-1]}/lidar_driver", f"/{prefix[:-1]}/camera_driver"}
        # Alive comes before the state is read: both start unconfigured, and only the left one moves.
        for key in ("ns-left.left.lidar_driver", "ns-right.right.lidar_driver"):
            wait_node(None, key, alive=True, state="unconfigured", timeout=10)
        response = transition(api, "ns-left.left.lidar_driver", "configure")
        assert response.status_code == 200, response.json()
        assert ManagedNode.objects.get(key="ns-left.left.lidar_driver").state_label == "inactive"
        assert ManagedNode.objects.get(key="ns-right.right.lidar_driver").state_label == "unconfigured"
    finally:
        for process in processes:
            process.stop()


def test_lan_a_host_whose_cable_is_pulled_is_shown_lost_within_5_s_and_back_when_plugged(lan):
    lost, back = pull_cable(lan.hosts["lan-r2"], keys("lan-r2", "lidar_driver,planner"), "LAN")
    assert lost is not None and lost < 5, f"lan-r2's nodes shown lost after {lost} s (bound: 5 s)"
    assert back is not None, f"lan-r2's nodes not alive again within {BACK_WAIT} s of the cable plugged back"


def test_lan_a_host_back_after_an_outage_longer_than_the_dds_lease(lan):
    """25 s without the cable: both sides drop the other's DDS participant (lease 20 s); once
    it is plugged back the robot's nodes must be alive again (a robot back from a dead spot)."""
    lost, back = pull_cable(lan.hosts["lan-r2"], keys("lan-r2", "lidar_driver,planner"), "LAN, 25 s outage",
                            hold=25)
    assert lost is not None
    assert back is not None, f"lan-r2's nodes not alive again within {BACK_WAIT} s of the cable plugged back"


# -- 2: a LAN without multicast: static peers ---------------------------------------------------

def test_lan_without_multicast_static_peers(api, site):
    fabric = site.fabric
    switch = fabric.switch("quiet", QUIET)
    site_leg = site.attach(switch, multicast=False)
    hosts = {name: fabric.host(name) for name in ("quiet-gw", "quiet-r1", "quiet-r2")}
    for octet, host in zip((10, 11, 12), hosts.values(), strict=True):
        fabric.plug(host, switch, octet, multicast=False)
        host.route(UPLINK, site_leg)
    switch.drop_multicast()
    gw, r1, r2 = hosts.values()
    for a, b in ((r1, gw), (gw, r1), (r2, gw)):
        assert netns.udp_probe(a, b) == {"multicast": False, "unicast": True}, f"{a} -> {b}"

    register("quiet-r1", stack.domain(16), gateway="net-quiet")
    register("quiet-r2", stack.domain(17), gateway="net-quiet")
    site.start_gateway("net-quiet", gw, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                       ROS_STATIC_PEERS=f"{r1.address};{r2.address}")
    processes = [
        launch(r1, "quiet-r1-nodes", stack.domain(16), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               ROS_STATIC_PEERS=gw.address),
        launch(r2, "quiet-r2-nodes", stack.domain(17), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               ROS_STATIC_PEERS=gw.address),
    ]
    try:
        discovered(keys("quiet-r1") + keys("quiet-r2"), ready(*processes),
                   "LAN without multicast (static peers): robots ready to 4 nodes on 2 hosts alive")
        for name in ("quiet-r1", "quiet-r2"):
            response = transition(api, f"{name}.lidar_driver", "configure")
            assert response.status_code == 200, response.json()
            assert ManagedNode.objects.get(key=f"{name}.lidar_driver").state_label == "inactive"
        lost, _ = pull_cable(r2, keys("quiet-r2"), "LAN without multicast", wait_back=False)
        assert lost is not None, f"quiet-r2's nodes not shown lost within {LOST_WAIT} s"
    finally:
        for process in processes:
            process.stop()


# -- 3: two subnets and a router ----------------------------------------------------------------

@dataclass
class Routed:
    hosts: dict[str, netns.Host]
    router: netns.Host


@pytest.fixture(scope="module")
def routed(site):
    """Subnet A (the site's host, a gateway's host) and subnet B (the robots' host, a second
    gateway's host) with a router between them; the router runs a Fast DDS discovery server."""
    fabric = site.fabric
    a, b = fabric.switch("sub-a", SUBNET_A), fabric.switch("sub-b", SUBNET_B)
    site_leg = site.attach(a)
    router = fabric.router("router")
    router_a, router_b = fabric.plug(router, a, 1), fabric.plug(router, b, 1)
    router.route(UPLINK, site_leg)
    site.host.route(SUBNET_B, router_a)  # replies to subnet B's gateway (the site's host forwards nothing)
    hosts = {"gw-a": fabric.host("gw-a"), "robots-b": fabric.host("robots-b"), "gw-b": fabric.host("gw-b")}
    fabric.plug(hosts["gw-a"], a, 10)
    hosts["gw-a"].route(UPLINK, site_leg)
    hosts["gw-a"].route(SUBNET_B, router_a)
    for octet, name in ((21, "robots-b"), (22, "gw-b")):
        fabric.plug(hosts[name], b, octet)
        hosts[name].route(UPLINK, router_b)
        hosts[name].route(SUBNET_A, router_b)
    # Multicast stays in its subnet; unicast is routed.
    assert netns.udp_probe(hosts["robots-b"], hosts["gw-a"]) == {"multicast": False, "unicast": True}
    venv = Path(sys.executable).parent
    libs = f"{sys.prefix}/lib:{sysconfig.get_paths()['purelib']}/ros_fastrtps.libs"
    server = router.start("discovery-server", [str(venv / "fast-discovery-server"), "-i", "0", "-l", "0.0.0.0",
                                               "-p", str(DS_PORT)], stack.environment(LD_LIBRARY_PATH=libs))
    stack.wait_for(lambda: "Server GUID prefix" in server.output() or not server.alive(), 15,
                   "the discovery server")
    assert server.alive(), server.tail()
    yield Routed(hosts, router)


def test_routed_robot_found_through_a_discovery_server(api, site, routed):
    router_a = routed.router.interfaces["eth0"].split("/")[0]
    router_b = routed.router.interfaces["eth1"].split("/")[0]
    register("route-ds", stack.domain(18), gateway="net-ds")
    site.start_gateway("net-ds", routed.hosts["gw-a"], ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET",
                       ROS_DISCOVERY_SERVER=f"{router_a}:{DS_PORT}", ROS_SUPER_CLIENT="TRUE")
    process = launch(routed.hosts["robots-b"], "route-ds-nodes", stack.domain(18),
                     ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET", ROS_DISCOVERY_SERVER=f"{router_b}:{DS_PORT}")
    try:
        discovered(keys("route-ds"), ready(process), "routed, discovery server: robot ready to 2 nodes alive")
        response = transition(api, "route-ds.lidar_driver", "configure")
        assert response.status_code == 200, response.json()
        assert ManagedNode.objects.get(key="route-ds.lidar_driver").state_label == "inactive"
        listed = {g["name"]: g for g in api.get("/api/v1/gateways").json()["gateways"]}
        assert "discovery server" in listed["net-ds"]["dds_summary"], listed["net-ds"]
        lost, _ = pull_cable(routed.hosts["robots-b"], keys("route-ds"), "routed, discovery server", wait_back=False)
        assert lost is not None, f"route-ds's nodes not shown lost within {LOST_WAIT} s"
    finally:
        process.stop()


def test_routed_a_gateway_in_the_robots_subnet_dials_the_site_across_the_router(api, site, routed):
    register("route-b", stack.domain(19), gateway="net-b")
    # DDS on the robots' subnet only (the gateway's interface white list), Redis across the router.
    site.start_gateway("net-b", routed.hosts["gw-b"], ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET",
                       LIFECYCLE_DDS_INTERFACES="eth0")
    process = launch(routed.hosts["robots-b"], "route-b-nodes", stack.domain(19),
                     ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET")
    try:
        discovered(keys("route-b"), ready(process), "routed, gateway per subnet: robot ready to 2 nodes alive")
        response = transition(api, "route-b.lidar_driver", "configure")
        assert response.status_code == 200, response.json()
        assert ManagedNode.objects.get(key="route-b.lidar_driver").state_label == "inactive"

        listed = {g["name"]: g for g in api.get("/api/v1/gateways").json()["gateways"]}
        for name, robot_name in (("net-ds", "route-ds"), ("net-b", "route-b")):
            assert listed[name]["online"], listed[name]
            assert robot_name in listed[name]["robots"], listed[name]
        page = api.get("/")
        assert page.status_code == 200
        text = page.content.decode()
        assert "Gateway net-ds" in text and "Gateway net-b" in text
        lost, _ = pull_cable(routed.hosts["robots-b"], keys("route-b"), "routed, gateway per subnet",
                             wait_back=False)
        assert lost is not None, f"route-b's nodes not shown lost within {LOST_WAIT} s"
    finally:
        process.stop()


def test_nothing_multicast_reached_the_root_namespace(site):
    """The root namespace's one link carried Redis and nothing else: no multicast frame came in."""
    counters = site.fabric.root_link_counters()
    assert counters["packets"] > 0, counters
    assert counters["multicast"] == 0, counters
