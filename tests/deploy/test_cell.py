"""A remote cell on the real engine: the site's plain compose file with its Redis published
(docker-compose.redis-public.yml), and a second project, the cell (docker/cell/), whose gateway
dials in to that Redis over a Docker network that stands in for the plant network, with the
env file `add_gateway` wrote inside the site's web container. Its robot is a container on the
cell's own DDS network; it is driven through the site's JSON API.

Nothing here leaves the machine: the plant network is a bridge of this engine, the site's
ports are published on loopback only.
"""
from __future__ import annotations

import http.client
import json
import os
import secrets
import shutil
import socket
import stat

import pytest

from tests.deploy import edge_stack, engine
from tests.deploy.edge_stack import Stack
from tests.deploy.engine import DOCKER_DIR

CELL = "cell-b"
CELL_ROBOT, CELL_DOMAIN = "cell-robot", 31  # the robot container of docker/cell/ (profile demo)
SITE_REDIS_ALIAS = "site-redis"  # the site's Redis as the plant network names it
NODES = ("joy_to_vel", "lidar_driver", "camera_driver", "planner")


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
def cell(image, scratch, timings):
    """The site (plain compose + public Redis) and the cell (its own project), both up."""
    pid = os.getpid()
    site_dir, cell_dir = scratch / "site", scratch / "cell"
    site_dir.mkdir()
    cell_dir.mkdir()
    for name in ("docker-compose.yml", "docker-compose.redis-public.yml"):
        shutil.copy(DOCKER_DIR / name, site_dir / name)
    shutil.copy(DOCKER_DIR / "cell" / "docker-compose.yml", cell_dir / "docker-compose.yml")
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
    (cell_dir / "docker-compose.plant.yml").write_text(_plant_override(plant, "gateway"))
    site = Stack(project=f"lcdeploy{pid}site", workdir=site_dir, web_port=web_port, logs="site-compose",
                 files=["docker-compose.yml", "docker-compose.redis-public.yml", "docker-compose.plant.yml"])
    remote = Stack(project=f"lcdeploy{pid}cell", workdir=cell_dir, web_port=0, logs="cell-compose",
                   files=["docker-compose.yml", "docker-compose.plant.yml"])
    site.extra.update(env=env, redis_port=redis_port, plant=plant)
    timings.record("stale_projects_removed", edge_stack.remove_stale_projects())
    try:
        # The plant network, labelled as the site's so that a killed run's leftovers are found.
        engine.run(["docker", "network", "create", "--label", f"com.docker.compose.project={site.project}", plant],
                   timeout=60)
        with timings.timed("cell_site_up_s"):
            site.compose("up", "-d", timeout=300)
            for service in ("web", "ingest", "gateway"):
                engine.wait_for(lambda s=service: site.health(s) == "healthy", 150,
                                f"the site's {service} to be healthy")
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
        token = site.manage("create_api_token", "admin", "--name", "cell test")
        site.extra["api"] = Site(web_port, token)
        with timings.timed("cell_up_s"):
            remote.compose("--profile", "demo", "up", "-d", timeout=300)
        yield site, remote
    finally:
        for stack in (remote, site):
            stack.save_logs()
        with timings.timed("cell_down_s"):
            remote.down()
            site.down()
            engine.run(["docker", "network", "rm", plant], timeout=60, check=False)
        left = remote.leftovers() + site.leftovers()
        networks = engine.run(["docker", "network", "ls", "-q", "--filter", f"name=^{plant}$"], timeout=60).stdout
        assert not left and not networks.strip(), f"left behind: {left} {networks.split()}"


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
