"""Remote cells on the real engine: the site's plain compose file with its Redis published
(docker-compose.redis-public.yml), and two kinds of cell whose gateways dial in to that Redis
over a Docker network that stands in for the plant network:

- docker/cell/ (a second project) with the env file `add_gateway` wrote inside the site's web
  container; its robot is a container on the cell's own DDS network;
- docker/edge-cell/ (the Industrial Edge package of a cell's gateway), configured only through
  the cfg-data/param.json an operator fills in from what `add_gateway` printed; its robot is a
  process on its own plant LAN behind the layer-2 network zzz_layer2_net1 (tests/deploy/layer2.py).

Both robots are driven through the site's JSON API. Nothing here leaves the machine: the plant
network is a bridge of this engine, the site's ports are published on loopback only, the
plant LAN is a network namespace.
"""
from __future__ import annotations

import http.client
import json
import os
import secrets
import shutil
import socket
import stat
from urllib.parse import urlsplit

import pytest

from tests import domains
from tests.deploy import edge_stack, engine, layer2
from tests.deploy.edge_stack import Stack
from tests.deploy.engine import DOCKER_DIR, IMAGE

CELL = "cell-b"
CELL_ROBOT, CELL_DOMAIN = "cell-robot", 31  # the robot container of docker/cell/ (profile demo)
SITE_REDIS_ALIAS = "site-redis"  # the site's Redis as the plant network names it
NODES = ("joy_to_vel", "lidar_driver", "camera_driver", "planner")
EDGE_CELL = "edge-cell-c"  # the Industrial Edge package of a cell's gateway (docker/edge-cell/)
EDGE_CELL_ROBOT, EDGE_CELL_DOMAIN = "edge-cell-agv", 33  # a robot process on that cell's plant LAN
EDGE_CELL_DIR = DOCKER_DIR / "edge-cell"


def _plant_override(network: str, service: str, alias: str | None = None) -> str:
    """A test-only compose file that puts ``service`` on the stand-in plant network."""
    entry = f"      plant:\n        aliases: [{alias}]\n" if alias else "      plant: {}\n"
    return (
        "version: '2.4'\nservices:\n"
        f"  {service}:\n    networks:\n{entry}"
        f"networks:\n  plant:\n    external: true\n    name: {network}\n"
    )


class Site:
    """The JSON API of the site's web container, on its loopback port."""

    def __init__(self, port: int, token: str = "") -> None:
        self.port, self.token = port, token

    def request(self, method: str, path: str, payload: dict | None = None) -> tuple[int, dict]:
        connection = http.client.HTTPConnection("127.0.0.1", self.port, timeout=30)
        headers = {"Host": "localhost", "Accept": "application/json", "Authorization": f"Bearer {self.token}"}
        body = None
        if payload is not None:
            body, headers["Content-Type"] = json.dumps(payload).encode(), "application/json"
        try:
            connection.request(method, path, body=body, headers=headers)
            response = connection.getresponse()
            return response.status, json.loads(response.read() or b"{}")
        finally:
            connection.close()

    def gateways(self) -> dict[str, dict]:
        status, body = self.request("GET", "/api/v1/gateways")
        assert status == 200, body
        return {g["name"]: g for g in body["gateways"]}

    def nodes(self, robot: str) -> dict[str, dict]:
        status, body = self.request("GET", f"/api/v1/nodes?robot={robot}")
        assert status == 200, body
        return {n["id"]: n for n in body["nodes"]}


@pytest.fixture(scope="module")
def site(image, scratch, timings):
    """The site (plain compose + public Redis) up, its Redis also on a Docker network that
    stands in for the plant network (alias site-redis); ``extra["api"]`` is its JSON API."""
    pid = os.getpid()
    site_dir = scratch / "site"
    site_dir.mkdir()
    for name in ("docker-compose.yml", "docker-compose.redis-public.yml"):
        shutil.copy(DOCKER_DIR / name, site_dir / name)
    plant = f"lcdeploy{pid}-plant"
    web_port, redis_port = engine.free_port(), engine.free_port()
    env = {
        "DJANGO_SUPERUSER_PASSWORD": "deploy-" + secrets.token_urlsafe(16),
        "DJANGO_ALLOWED_HOSTS": "localhost,127.0.0.1",
        "LIFECYCLE_HTTP_BIND": "127.0.0.1",
        "LIFECYCLE_HTTP_PORT": str(web_port),
        "REDIS_PASSWORD": secrets.token_hex(24),
        "LIFECYCLE_REDIS_BIND": "127.0.0.1",  # loopback here; the plant network's address on a site
        "LIFECYCLE_REDIS_PORT": str(redis_port),
    }
    dotenv = site_dir / ".env"
    dotenv.write_text("".join(f"{k}={v}\n" for k, v in env.items()))
    dotenv.chmod(0o600)
    (site_dir / "docker-compose.plant.yml").write_text(_plant_override(plant, "redis", SITE_REDIS_ALIAS))
    site = Stack(project=f"lcdeploy{pid}site", workdir=site_dir, web_port=web_port, logs="site-compose",
                 files=["docker-compose.yml", "docker-compose.redis-public.yml", "docker-compose.plant.yml"])
    site.extra.update(env=env, redis_port=redis_port, plant=plant)
    timings.record("stale_projects_removed", edge_stack.remove_stale_projects())
    timings.record("stale_plant_lans_removed", layer2.remove_stale())
    try:
        # The plant network, labelled as the site's so that a killed run's leftovers are found.
        engine.run(["docker", "network", "create", "--label", f"com.docker.compose.project={site.project}", plant],
                   timeout=60)
        with timings.timed("cell_site_up_s"):
            site.compose("up", "-d", timeout=300)
            for service in ("web", "ingest", "gateway"):
                engine.wait_for(lambda s=service: site.health(s) == "healthy", 150,
                                f"the site's {service} to be healthy")
        token = site.manage("create_api_token", "admin", "--name", "cell test")
        site.extra["api"] = Site(web_port, token)
        yield site
    finally:
        site.save_logs()
        with timings.timed("cell_site_down_s"):
            site.down()
            engine.run(["docker", "network", "rm", plant], timeout=60, check=False)
        left = site.leftovers()
        networks = engine.run(["docker", "network", "ls", "-q", "--filter", f"name=^{plant}$"], timeout=60).stdout
        assert not left and not networks.strip(), f"left behind: {left} {networks.split()}"


@pytest.fixture(scope="module")
def cell(site, scratch, timings):
    """The cell (docker/cell/, its own project) up, with the env file add_gateway wrote."""
    cell_dir = scratch / "cell"
    cell_dir.mkdir()
    shutil.copy(DOCKER_DIR / "cell" / "docker-compose.yml", cell_dir / "docker-compose.yml")
    (cell_dir / "docker-compose.plant.yml").write_text(_plant_override(site.extra["plant"], "gateway"))
    remote = Stack(project=f"lcdeploy{os.getpid()}cell", workdir=cell_dir, web_port=0, logs="cell-compose",
                   files=["docker-compose.yml", "docker-compose.plant.yml"])
    try:
        # What an operator does on the site: register the cell's gateway (its env file is written
        # inside the web container, then copied out) and the cell's robot.
        site.manage("add_gateway", CELL, "--redis-url", f"redis://{SITE_REDIS_ALIAS}:6379/0",
                    "--env-file", "/tmp/cell.env", "--description", "deploy test cell")
        web = site.container("web")
        engine.run(["docker", "cp", f"{web}:/tmp/cell.env", str(cell_dir / "cell.env")], timeout=60)
        engine.run(["docker", "exec", web, "rm", "/tmp/cell.env"], timeout=60)
        dds = [line for line in (DOCKER_DIR / "cell" / "env.example").read_text().splitlines()
               if line.startswith("ROS_")]
        with open(cell_dir / "cell.env", "a") as handle:
            handle.write("\n".join(dds) + "\n")
        site.manage("add_robot", CELL_ROBOT, "--domain", str(CELL_DOMAIN), "--gateway", CELL)
        with timings.timed("cell_up_s"):
            remote.compose("--profile", "demo", "up", "-d", timeout=300)
        yield site, remote
    finally:
        remote.save_logs()
        with timings.timed("cell_down_s"):
            remote.down()
        left = remote.leftovers()
        assert not left, f"left behind: {left}"


def test_env_file_from_add_gateway(cell, scratch):
    """add_gateway wrote the gateway's name and its own Redis user, readable by its owner only."""
    path = scratch / "cell" / "cell.env"
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    env = dict(line.split("=", 1) for line in path.read_text().splitlines() if "=" in line)
    assert env["LIFECYCLE_GATEWAY_NAME"] == CELL
    assert env["REDIS_URL"].startswith(f"redis://gw-{CELL}:") and env["REDIS_URL"].endswith(
        f"@{SITE_REDIS_ALIAS}:6379/0"), "the gateway's own user, the site's Redis as the plant network names it"
    site, _ = cell
    assert site.extra["env"]["REDIS_PASSWORD"] not in path.read_text(), "never the default user's password"


def test_cell_gateway_comes_online(cell):
    site, remote = cell
    api = site.extra["api"]

    def online():
        gateways = api.gateways()
        return gateways if gateways.get(CELL, {}).get("online") and gateways.get("local", {}).get("online") else None

    gateways = engine.wait_for(online, 120, f"gateways {CELL} and local online in /api/v1/gateways", interval=1)
    assert gateways[CELL]["robots"] == [CELL_ROBOT]
    assert gateways[CELL]["dds"].get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "SUBNET"
    assert gateways[CELL]["host"] != gateways["local"]["host"], "two gateway containers"
    engine.wait_for(lambda: remote.health("gateway") == "healthy", 90, "the cell's gateway to be healthy")


def test_cell_robot_discovered_and_driven_through_the_site(cell):
    site, _ = cell
    api = site.extra["api"]
    wanted = {f"{CELL_ROBOT}.{name}" for name in NODES}

    def alive():
        nodes = api.nodes(CELL_ROBOT)
        return nodes if all(nodes.get(k, {}).get("alive") for k in wanted) else None

    nodes = engine.wait_for(alive, 120, f"the cell robot's nodes {sorted(wanted)} alive", interval=1)
    key = f"{CELL_ROBOT}.lidar_driver"
    assert nodes[key]["state"]["label"] == "unconfigured", nodes[key]
    status, result = api.request("POST", f"/api/v1/nodes/{key}/transition", {"transition": "configure"})
    assert status == 200 and result["success"], result
    assert result["to"]["label"] == "inactive"
    status, body = api.request("GET", f"/api/v1/transitions?node={key}")
    assert status == 200, body
    records = body["transitions"]
    assert records and records[0]["outcome"] == "succeeded" and records[0]["source"] == "api", records[:1]
    assert records[0]["id"] == result["record_id"], "the audit record exists when the answer arrives"
    assert api.nodes(CELL_ROBOT)[key]["state"]["label"] == "inactive"


def test_cell_gateway_has_only_its_own_keys_and_no_database(cell):
    """Its Redis user may read its own heartbeat, not another gateway's; it has no volume."""
    site, remote = cell
    gateway = remote.container("gateway")
    probe = (
        "import os, redis\n"
        "r = redis.Redis.from_url(os.environ['REDIS_URL'])\n"
        f"print('own', r.get('lifecycle:gw:{CELL}:beat') is not None)\n"
        "try:\n"
        "    r.get('lifecycle:gw:local:beat'); print('other readable')\n"
        "except redis.exceptions.NoPermissionError:\n"
        "    print('other refused')\n"
    )
    out = engine.run(["docker", "exec", gateway, "python", "-c", probe], timeout=60).stdout.split("\n")
    assert out[:2] == ["own True", "other refused"], out
    mounts = json.loads(engine.run(["docker", "inspect", "-f", "{{json .Mounts}}", gateway], timeout=30).stdout)
    assert all(m["Type"] == "bind" and m["Destination"] == "/ca" for m in mounts), mounts
    no_database = "test ! -e /data/db.sqlite3 && test ! -e /tmp/gateway/db.sqlite3"
    engine.run(["docker", "exec", gateway, "sh", "-c", no_database], timeout=30)


def test_published_redis_wants_the_password(cell):
    """The site's Redis on its published port: the default user needs REDIS_PASSWORD."""
    site, _ = cell

    def say(*commands: bytes) -> bytes:
        with socket.create_connection(("127.0.0.1", site.extra["redis_port"]), timeout=10) as conn:
            conn.sendall(b"".join(commands))
            reply = b""
            while reply.count(b"\r\n") < len(commands):
                chunk = conn.recv(256)
                if not chunk:
                    break
                reply += chunk
            return reply

    assert say(b"PING\r\n").startswith(b"-NOAUTH"), "published Redis must refuse the default user without password"
    password = site.extra["env"]["REDIS_PASSWORD"].encode()
    assert say(b"AUTH " + password + b"\r\n", b"PING\r\n") == b"+OK\r\n+PONG\r\n"


# ---------------------------------------------------------------------------------------
# The Industrial Edge package of a cell's gateway (docker/edge-cell/)


@pytest.fixture(scope="module")
def edge_cell(site, scratch, timings):
    """docker/edge-cell/ as a device runs it: the compose file unchanged (plus a test-only file
    that puts the gateway on the plant network's stand-in, where the site's Redis is), its
    settings only in cfg-data/param.json, written from what `add_gateway` printed; a plant LAN
    of its own behind zzz_layer2_net1 with a robot process in it."""
    pid = os.getpid()
    workdir = scratch / "edge-cell"
    (workdir / "cfg-data").mkdir(parents=True)
    shutil.copy(EDGE_CELL_DIR / "docker-compose.yml", workdir / "docker-compose.yml")
    (workdir / "docker-compose.plant.yml").write_text(_plant_override(site.extra["plant"], "gateway"))
    remote = Stack(project=f"lcdeploy{pid}edgecell", workdir=workdir, web_port=0, logs="edge-cell-compose",
                   files=["docker-compose.yml", "docker-compose.plant.yml"])
    lan = layer2.PlantLan("b", label=f"lcdeploy{pid}cellplant", log_dir=scratch / "plant-b")
    domains.claim([EDGE_CELL_DOMAIN])
    try:
        # The operator on the site: register the gateway; what it prints goes into the device's
        # app configuration (the IEM's form), nowhere else.
        printed = site.manage("add_gateway", EDGE_CELL, "--redis-url", f"redis://{SITE_REDIS_ALIAS}:6379/0",
                              "--description", "deploy test: Industrial Edge cell")
        lines = dict(line.split("=", 1) for line in printed.splitlines() if "=" in line)
        config = {
            "gateway": {"name": lines["LIFECYCLE_GATEWAY_NAME"], "channelPrefix": lines["LIFECYCLE_CHANNEL_PREFIX"]},
            "redis": {"url": lines["REDIS_URL"]},
            "ros": {"discoveryRange": "SUBNET", "staticPeers": "", "discoveryServer": "", "serviceTimeout": 5},
        }
        (workdir / "cfg-data" / "param.json").write_text(json.dumps(config, indent=2))
        remote.extra["password"] = urlsplit(lines["REDIS_URL"]).password
        site.manage("add_robot", EDGE_CELL_ROBOT, "--domain", str(EDGE_CELL_DOMAIN), "--gateway", EDGE_CELL)
        with timings.timed("edge_cell_plant_lan_up_s"):
            lan.create()
            lan.robot(EDGE_CELL_ROBOT, EDGE_CELL_DOMAIN)
        with timings.timed("edge_cell_up_s"):
            remote.compose("up", "-d", timeout=300)
        remote.extra["lan"] = lan
        yield remote
    finally:
        remote.save_logs()
        with timings.timed("edge_cell_down_s"):
            remote.down()
            lan.close()
        domains.release([EDGE_CELL_DOMAIN])
        left = remote.leftovers() + lan.leftovers()
        assert not left, f"left behind: {left}"


def test_edge_cell_is_configured_only_through_cfg_data(edge_cell):
    """Name and Redis URL are in cfg-data only: not in the compose file, not in the container's
    environment, not in its logs (the entrypoint names the Redis host only)."""
    compose = (EDGE_CELL_DIR / "docker-compose.yml").read_text()
    assert "REDIS_URL" not in compose and EDGE_CELL not in compose
    gateway = edge_cell.container("gateway")
    details = engine.run(["docker", "inspect", gateway], timeout=30).stdout
    env = json.loads(details)[0]["Config"]["Env"]
    assert not any(item.startswith(("REDIS_URL=", "LIFECYCLE_GATEWAY_NAME=")) for item in env), env
    password = edge_cell.extra["password"]
    assert password and password not in details
    logs = edge_cell.compose("logs", "--no-color", "gateway", timeout=60)
    assert password not in logs.stdout + logs.stderr
    assert f"gateway {EDGE_CELL}, Redis at {SITE_REDIS_ALIAS}:6379/0" in logs.stdout + logs.stderr


def test_edge_cell_gateway_comes_online(site, edge_cell):
    """Online at the site beside the other gateways; healthy by its own check (which reads the
    Redis URL from cfg-data as the entrypoint did)."""
    api = site.extra["api"]

    def online():
        gateways = api.gateways()
        return gateways if gateways.get(EDGE_CELL, {}).get("online") else None

    gateways = engine.wait_for(online, 120, f"gateway {EDGE_CELL} online in /api/v1/gateways", interval=1)
    assert gateways[EDGE_CELL]["robots"] == [EDGE_CELL_ROBOT]
    assert gateways[EDGE_CELL]["dds"].get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "SUBNET"
    engine.wait_for(lambda: edge_cell.health("gateway") == "healthy", 90, "the edge cell's gateway to be healthy")


def test_edge_cell_robot_driven_through_the_site(site, edge_cell, timings):
    """The robot on the cell's plant LAN, found over the layer-2 network, driven through the
    site's API; the audit record is there with the answer. Memory under the package's limit."""
    api = site.extra["api"]
    wanted = {f"{EDGE_CELL_ROBOT}.{name}" for name in ("lidar_driver", "camera_driver")}

    def alive():
        nodes = api.nodes(EDGE_CELL_ROBOT)
        return nodes if all(nodes.get(k, {}).get("alive") for k in wanted) else None

    nodes = engine.wait_for(alive, 120, f"the edge cell robot's nodes {sorted(wanted)} alive", interval=1)
    key = f"{EDGE_CELL_ROBOT}.camera_driver"
    assert nodes[key]["state"]["label"] == "unconfigured", nodes[key]
    status, result = api.request("POST", f"/api/v1/nodes/{key}/transition", {"transition": "configure"})
    assert status == 200 and result["success"], result
    assert result["to"]["label"] == "inactive"
    status, body = api.request("GET", f"/api/v1/transitions?node={key}")
    assert status == 200 and body["transitions"][0]["id"] == result["record_id"], body
    limit = edge_stack.mem_limit_bytes(edge_stack.yaml_services(EDGE_CELL_DIR / "docker-compose.yml")["gateway"]
                                       ["mem_limit"])
    usage = engine.run(["docker", "stats", "--no-stream", "--format", "{{.MemUsage}}", edge_cell.container("gateway")],
                       timeout=60).stdout.strip()
    used, enforced = (edge_stack.stats_bytes(part) for part in usage.split("/"))
    assert abs(enforced - limit) < 2**20 and used < limit, usage
    timings.record("edge_cell_gateway_memory_mib", round(used / 2**20, 1))


@pytest.mark.parametrize(
    "config, message",
    [
        ({}, "no Redis URL"),
        ({"gateway": {"name": "cell-x"}, "redis": {"url": "redis://gw-cell-y:secretsecret@site:6379/0"}},
         "belongs to the gateway 'cell-y'"),
        ({"gateway": {"name": "cell-x"}, "redis": {"url": "redis://site:6379/0"}}, "no password"),
        ({"gateway": {"name": "cell-x"}, "redis": {"url": "http://site"}}, "redis.url must look like"),
        ({"gateway": {"name": "cell-x"}, "redis": {"url": "redis://gw-cell-x:p@site:6379/0"},
          "ros": {"discoveryServer": "10.0.0.1:99999"}}, "ros.discoveryServer"),
    ],
)
def test_edge_cell_refuses_a_bad_configuration(config, message, image, tmp_path):
    """The image's gateway role with a bad cfg-data: exit 78, the reason in its log, no secret."""
    folder = tmp_path / "cfg-data"
    folder.mkdir()
    (folder / "param.json").write_text(json.dumps(config))
    folder.chmod(0o755)
    (folder / "param.json").chmod(0o644)
    result = engine.run(["docker", "run", "--rm", "--network", "none", "-v", f"{folder}:/cfg-data:ro", IMAGE,
                         "gateway"], timeout=120, check=False)
    assert result.returncode == 78 and message in result.stderr, (result.returncode, result.stderr)
    assert "secretsecret" not in result.stderr
