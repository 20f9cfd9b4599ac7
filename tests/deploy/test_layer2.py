"""The Industrial Edge app's gateway on the device's layer-2 network (zzz_layer2_net1): a robot
process on the plant LAN (a network namespace behind a veth, the macvlan's parent; see
tests/deploy/layer2.py) is found by the gateway container and driven through the app, and its
DDS multicast stays on the plant LAN. Without the layer-2 network the app does not start."""
from __future__ import annotations

import ipaddress
import json
import sys

import pytest

from tests.deploy import engine, layer2
from tests.deploy.client import Browser
from tests.deploy.engine import PLANT_DOMAIN, PLANT_ROBOT

PREFIX = "/lifecycle"
NODES = ("lidar_driver", "camera_driver")  # what the plant robot runs (layer2.PlantLan.robot)


@pytest.fixture(scope="module")
def api(stack) -> tuple[Browser, str]:
    """The JSON API through the nginx that stands in for the device's reverse proxy."""
    token = stack.manage("create_api_token", "admin", "--name", "layer-2 test")
    return Browser("127.0.0.1", stack.proxy_port), token


def plant_nodes(api) -> dict[str, dict]:
    browser, token = api
    response = browser.api("GET", f"{PREFIX}/api/v1/nodes?robot={PLANT_ROBOT}", token)
    assert response.status == 200, response
    return {node["id"]: node for node in response.json()["nodes"]}


def wait_plant_nodes(api, timeout: float = 90) -> dict[str, dict]:
    wanted = {f"{PLANT_ROBOT}.{name}" for name in NODES}

    def alive():
        nodes = plant_nodes(api)
        return nodes if all(nodes.get(key, {}).get("alive") for key in wanted) else None

    return engine.wait_for(alive, timeout, f"the plant robot's nodes {sorted(wanted)} alive", interval=1)


def test_without_the_layer2_network_the_app_does_not_start(stack):
    """What a device without layer-2 access does with the app: compose refuses it, naming the
    network, before any container exists (the operator must enable layer-2 access first)."""
    returncode, output, leftovers = stack.extra["without_layer2"]
    assert returncode != 0, output
    assert f"Network {layer2.NETWORK} declared as external, but could not be found" in output, output
    assert not [item for item in leftovers if item.startswith("container")], leftovers


def test_layer2_network_is_a_macvlan_over_the_plant_lan(stack):
    plant = stack.extra["plant"]
    network = json.loads(engine.run(["docker", "network", "inspect", layer2.NETWORK], timeout=30).stdout)[0]
    assert network["Driver"] == "macvlan" and network["Options"]["parent"] == plant.parent, network
    (ipam,) = network["IPAM"]["Config"]
    assert ipam["Subnet"] == layer2.SUBNET and ipam["IPRange"] == layer2.IP_RANGE
    link = plant.link_info()
    assert link == {"up": True, "ipv4": [], "master": False, "veth": True}, (
        f"the macvlan's parent must be up, without address, in no bridge, the veth to the plant LAN: {link}")
    members = {c["Name"]: c["IPv4Address"] for c in network["Containers"].values()}
    gateway = engine.run(["docker", "inspect", "-f", "{{.Name}}", stack.container("gateway")], timeout=30)
    gateway_name = gateway.stdout.strip().lstrip("/")
    assert set(members) == {gateway_name}, f"only the gateway joins the plant LAN: {members}"
    address = ipaddress.ip_interface(members[gateway_name]).ip
    assert address in ipaddress.ip_network(layer2.IP_RANGE), f"Docker's range, not the robots': {address}"


def test_gateway_container_reaches_the_plant_lan(stack):
    """Unicast from the gateway container over the macvlan and the veth to a host of the plant
    LAN (a macvlan child cannot reach its parent, but the plant LAN is behind the parent)."""
    plant = stack.extra["plant"]
    port = 18080
    server = plant.start("http-probe", [sys.executable, "-m", "http.server", str(port), "--bind", "10.232.0.10"],
                         env={"PATH": "/usr/bin:/bin", "PYTHONUNBUFFERED": "1"})
    try:
        probe = (f"import urllib.request\n"
                 f"print(urllib.request.urlopen('http://10.232.0.10:{port}/', timeout=5).status)\n")
        result = engine.wait_for(
            lambda: engine.run(["docker", "exec", stack.container("gateway"), "python", "-c", probe],
                               timeout=30).stdout.strip() == "200", 30, "the gateway container to reach 10.232.0.10")
        assert result
    finally:
        server.terminate()
        server.wait(10)


def test_gateway_finds_the_plant_robot(stack, api):
    """Discovery by multicast on the plant LAN (SUBNET on both sides): the robot's nodes are
    listed alive through the device's proxy stand-in, under the gateway local."""
    nodes = wait_plant_nodes(api)
    assert {n["robot"] for n in nodes.values()} == {PLANT_ROBOT}
    assert nodes[f"{PLANT_ROBOT}.lidar_driver"]["state"]["label"] in ("unconfigured", "inactive", "active")
    browser, token = api
    gateways = {g["name"]: g for g in browser.api("GET", f"{PREFIX}/api/v1/gateways", token).json()["gateways"]}
    assert PLANT_ROBOT in gateways["local"]["robots"]
    assert gateways["local"]["dds"].get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "SUBNET"


def test_transition_of_the_plant_robot_through_the_web_container(stack, api):
    """`manage.py lifecycle set` in the web container: Redis, the gateway container, DDS over
    the macvlan to the robot in the plant LAN; the audit record is there when it returns."""
    wait_plant_nodes(api)
    key = f"{PLANT_ROBOT}.lidar_driver"
    state = plant_nodes(api)[key]["state"]["label"]
    step = {"unconfigured": "configure", "inactive": "activate", "active": "deactivate"}[state]
    output = stack.manage("lifecycle", "set", key, step, "--user", "admin")
    assert output == "Transitioning successful", output
    browser, token = api
    records = browser.api("GET", f"{PREFIX}/api/v1/transitions?node={key}", token).json()["transitions"]
    assert records and records[0]["source"] == "cli" and records[0]["outcome"] == "succeeded", records[:1]
    assert records[0]["transition"]["label"] == step
    expected = {"configure": "inactive", "activate": "active", "deactivate": "inactive"}[step]
    assert plant_nodes(api)[key]["state"]["label"] == expected


def test_plant_multicast_stays_off_the_machines_interfaces(stack, api):
    """Listen on every interface of the root namespace while the robot and the gateway talk:
    the plant LAN's DDS (its addresses, its domain's ports) shows on the macvlan's parent only,
    never on an interface that leads off this machine (nor on anyone else's)."""
    wait_plant_nodes(api)
    plant = stack.extra["plant"]
    seen = layer2.sniff(8, [PLANT_DOMAIN])
    ours = seen.pop(plant.parent, [])
    assert any(src == "10.232.0.10" and dst == layer2.DDS_MULTICAST for src, dst, _ in ours), (
        f"the robot's discovery multicast should show on {plant.parent} (the sniffer works): {ours[:5]}")
    outside = {name: packets for name, packets in seen.items()
               if name in layer2.machine_interfaces(exclude={plant.parent})}
    assert not outside, f"plant LAN traffic on the machine's interfaces: { {k: v[:5] for k, v in outside.items()} }"
