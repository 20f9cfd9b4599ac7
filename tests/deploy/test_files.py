"""The deployment files themselves: compose files valid for docker-compose (format 2.4), the
Industrial Edge rules kept, the roles of the services (a gateway without database), no secret
in any compose file or env example, the reverse-proxy entry, one version everywhere. The app
configuration (templates and config.py) is tested in test_runtime_config.py."""
from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path
from urllib.parse import urlsplit

import pytest
import yaml

from tests.deploy import edge_stack, engine
from tests.deploy.engine import DOCKER_DIR, EDGE_DIR, IMAGE, VERSION

CELL_DIR = DOCKER_DIR / "cell"
EDGE_CELL_DIR = DOCKER_DIR / "edge-cell"
COMPOSE_FILES = {
    "plain": [DOCKER_DIR / "docker-compose.yml"],
    "plain+redis-public": [DOCKER_DIR / "docker-compose.yml", DOCKER_DIR / "docker-compose.redis-public.yml"],
    "edge": [EDGE_DIR / "docker-compose.yml"],
    "edge+demo": [EDGE_DIR / "docker-compose.yml", EDGE_DIR / "docker-compose.demo.yml"],
    "edge-no-layer2+demo": [EDGE_DIR / "docker-compose.no-layer2.yml", EDGE_DIR / "docker-compose.demo.yml"],
    "cell": [CELL_DIR / "docker-compose.yml"],
    "cell-host-supervisor": [CELL_DIR / "docker-compose.host-supervisor.yml"],
    "edge-cell": [EDGE_CELL_DIR / "docker-compose.yml"],
}
# What is handed to the Industrial Edge Publisher (an override is checked merged into its app).
PUBLISHER_FILES = {
    "edge": [EDGE_DIR / "docker-compose.yml"],
    "edge+demo": [EDGE_DIR / "docker-compose.yml", EDGE_DIR / "docker-compose.demo.yml"],
    "edge-no-layer2": [EDGE_DIR / "docker-compose.no-layer2.yml"],
    "edge-cell": [EDGE_CELL_DIR / "docker-compose.yml"],
}
LAYER2 = "zzz_layer2_net1"
# Every compose file and env example in docker/ (found, not listed: a new one is checked too).
ALL_COMPOSE = sorted(DOCKER_DIR.glob("**/docker-compose*.yml"))
ALL_ENV_EXAMPLES = sorted(DOCKER_DIR.glob("**/env.example"))
APP_MEMORY_BUDGET = 500 * 1024**2  # the thesis' single container had 500 MB; the whole app fits in it


def load(path):
    return yaml.safe_load(path.read_text())


@pytest.mark.parametrize("name", list(COMPOSE_FILES))
def test_compose_file_validates(name, docker_engine, tmp_path):
    """`docker-compose config` accepts the file (it rejects unknown keys and bad values), in a
    copy of its folder (the cell's needs its env file: env.example stands in)."""
    folder = tmp_path / name
    shutil.copytree(COMPOSE_FILES[name][0].parent, folder, ignore=shutil.ignore_patterns("build", ".env"))
    if name.startswith("cell"):
        shutil.copy(CELL_DIR / "env.example", folder / "cell.env")
    argv = ["docker-compose"]
    for path in COMPOSE_FILES[name]:
        argv += ["-f", str(folder / path.name)]
    if name in ("plain", "cell"):
        argv += ["--profile", "demo"]
    environment = {k: v for k, v in os.environ.items() if not k.startswith(("REDIS_", "LIFECYCLE_", "DJANGO_"))}
    if name == "plain+redis-public":
        # Without the password the override refuses to start (no published Redis without it).
        refused = engine.run(argv + ["config", "-q"], timeout=60, cwd=folder, env=environment, check=False)
        assert refused.returncode != 0 and "REDIS_PASSWORD" in refused.stderr, refused.stderr
        environment["REDIS_PASSWORD"] = "x" * 16
    engine.run(argv + ["config", "-q"], timeout=60, cwd=folder, env=environment)


@pytest.mark.parametrize("name", list(PUBLISHER_FILES))
def test_edge_compose_follows_industrial_edge_rules(name):
    paths = PUBLISHER_FILES[name]
    for path in paths:
        assert str(load(path)["version"]) == "2.4", path.name
        assert not re.search(r"^\s*build:", path.read_text(), re.M), f"{path.name}: no build key for the Publisher"
    for name, service in edge_stack.yaml_services(*paths).items():
        where = f"{paths[-1].name}: service {name}"
        assert service["image"] == IMAGE, f"{where}: image must be {IMAGE} (docker/VERSION)"
        assert not service["image"].endswith(":latest") and ":" in service["image"], f"{where}: explicit tag"
        assert "build" not in service, f"{where}: no build key for the Publisher"
        assert "mem_limit" in service, f"{where}: mem_limit is mandatory"
        assert service.get("restart") in ("always", "unless-stopped", "on-failure"), where
        assert service.get("network_mode") != "host" and not service.get("privileged"), where
        assert "ports" not in service, f"{where}: the UI is reached through the device's proxy only"
        logging = service.get("logging", {})
        assert logging.get("driver") == "json-file", where
        assert {"max-size", "max-file"} <= set(logging.get("options", {})), where
        for volume in service.get("volumes", []):
            source = volume.split(":")[0]
            assert source.startswith("./") or re.fullmatch(r"[a-z][a-z0-9_-]*", source), f"{where}: {volume}"
        for key, value in (service.get("environment") or {}).items():
            assert not SECRET_NAME.search(key) and "@" not in str(value), f"{where}: {key}: secrets belong in cfg-data"


def test_no_app_makes_a_macvlan():
    """The layer-2 network is the device's (external); no compose file creates a macvlan or
    any network over a host interface."""
    for path in ALL_COMPOSE:
        for name, network in (load(path).get("networks") or {}).items():
            network = network or {}
            assert network.get("driver", "bridge") == "bridge" or network.get("external"), f"{path.name}: {name}"
            assert "parent" not in (network.get("driver_opts") or {}), f"{path.name}: {name}"
            if name == LAYER2 or network.get("name") == LAYER2:
                assert network == {"external": True, "name": LAYER2}, f"{path.name}: {name} must be the device's"


def assert_site_roles(services: dict, where: str) -> None:
    """web + ingest + gateway "local" + redis; only web and ingest have the database's volume,
    the gateway has none (Redis only), redis keeps its append-only file in a volume of its own."""
    assert {"web", "ingest", "gateway", "redis"} <= set(services), where
    for name in ("web", "ingest", "gateway", "redis"):
        assert services[name]["command"] == [name], f"{where}: {name} runs the role {name}"
    for name in ("web", "ingest"):
        assert any(v.startswith("lifecycle-data:/data") for v in services[name]["volumes"]), f"{where}: {name}"
    gateway = services["gateway"]
    assert gateway["environment"]["LIFECYCLE_GATEWAY_NAME"] == "local", where
    assert not any(v.split(":")[0] in ("lifecycle-data", "redis-data") for v in gateway.get("volumes", [])), (
        f"{where}: the gateway has no database and needs no data volume")
    assert "LIFECYCLE_DATA_DIR" not in gateway["environment"] and "DATABASE_URL" not in gateway["environment"]
    assert "web" not in gateway.get("depends_on", []), f"{where}: the gateway does not wait for the site"
    assert "redis-data:/data" in services["redis"]["volumes"], f"{where}: Redis keeps its streams in a volume"
    assert "REDIS_MAXMEMORY" in services["redis"]["environment"], where


@pytest.mark.parametrize("filename", ["docker-compose.yml", "docker-compose.no-layer2.yml"])
def test_edge_app_layout(filename):
    compose = load(EDGE_DIR / filename)
    services, networks = compose["services"], compose["networks"]
    assert set(services) == {"web", "ingest", "gateway", "redis"}
    assert_site_roles(services, "edge")
    assert networks["proxy-redirect"] == {"external": True}
    assert services["web"]["networks"] == ["proxy-redirect", "lifecycle"], "web: the device's proxy and Redis only"
    assert all("proxy-redirect" not in s.get("networks", []) for n, s in services.items() if n != "web")
    assert networks["lifecycle"].get("internal") is True, "the app's own services talk on an internal network"
    assert "redis" in [n for n in services if "lifecycle" in services[n]["networks"]]
    assert "lifecycle" in services["gateway"]["networks"], "the gateway reaches Redis"
    if filename == "docker-compose.yml":
        assert services["gateway"]["networks"] == ["lifecycle", LAYER2], "DDS on the plant LAN (layer 2)"
        assert networks[LAYER2] == {"external": True, "name": LAYER2}
        assert all(LAYER2 not in s["networks"] for n, s in services.items() if n != "gateway")
        assert services["gateway"]["environment"]["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SUBNET"
    else:
        assert LAYER2 not in networks and all(LAYER2 not in s["networks"] for s in services.values())
    # The demo robot shares the network "ros" with the gateway (the override adds it).
    demo = edge_stack.yaml_services(EDGE_DIR / filename, EDGE_DIR / "docker-compose.demo.yml")
    assert "ros" in demo["gateway"]["networks"] and demo["robot-agv1"]["networks"] == ["ros"]
    for name in ("web", "ingest", "gateway"):
        assert "./cfg-data/:/cfg-data/:ro" in services[name]["volumes"], f"{name} reads the app configuration"
    assert {"lifecycle-data", "redis-data"} <= set(compose["volumes"])
    total = sum(edge_stack.mem_limit_bytes(s["mem_limit"]) for s in services.values())
    assert total <= APP_MEMORY_BUDGET, f"the app's memory limits add up to {total / 2**20:.0f} MiB"
    # The header comment states the same figures.
    stated = re.search(r"^# Memory: ([\d +]+) = (\d+) MB", (EDGE_DIR / filename).read_text(), re.M)
    assert stated, "the header comment states the app's memory total"
    limits = [edge_stack.mem_limit_bytes(s["mem_limit"]) // 2**20 for s in services.values()]
    assert [int(x) for x in stated.group(1).split("+")] == limits and int(stated.group(2)) == total // 2**20
    for name, service in services.items():
        keys = " ".join(service.get("environment", {})).upper()
        assert "PASSWORD" not in keys and "SECRET" not in keys, f"{name}: secrets belong in cfg-data"


def test_no_layer2_variant_is_the_app_without_it():
    """docker-compose.no-layer2.yml: docker-compose.yml with the gateway on the app's own
    network "ros" instead of the layer-2 network, nothing else changed."""
    app, variant = load(EDGE_DIR / "docker-compose.yml"), load(EDGE_DIR / "docker-compose.no-layer2.yml")
    app["services"]["gateway"]["networks"] = ["lifecycle", "ros"]
    del app["networks"][LAYER2]
    app["networks"]["ros"] = {"driver": "bridge"}
    assert variant == app


def test_edge_cell_package_is_a_gateway_only():
    """docker/edge-cell/: the gateway alone, on the layer-2 network and a bridge of its own (the
    way out to the site), every setting and secret from cfg-data, compose 2.4, memory limited."""
    compose = load(EDGE_CELL_DIR / "docker-compose.yml")
    assert str(compose["version"]) == "2.4"
    services, networks = compose["services"], compose["networks"]
    assert set(services) == {"gateway"}
    gateway = services["gateway"]
    assert gateway["command"] == ["gateway"] and gateway["image"] == IMAGE
    assert edge_stack.mem_limit_bytes(gateway["mem_limit"]) <= 256 * 2**20 and "mem_reservation" in gateway
    assert gateway["volumes"] == ["./cfg-data/:/cfg-data/:ro"], "its configuration only: no data volume"
    assert "env_file" not in gateway and set(gateway.get("environment", {})) <= {"ROS_AUTOMATIC_DISCOVERY_RANGE"}, (
        "name, Redis URL and password come from cfg-data only")
    assert gateway["networks"] == ["uplink", LAYER2] and sorted(gateway["networks"]) == gateway["networks"], (
        "the uplink sorts first: the default route (to the site) stays on it")
    assert networks[LAYER2] == {"external": True, "name": LAYER2}
    assert networks["uplink"] == {"driver": "bridge"}, "not internal: it is the way to the site's Redis"
    assert "proxy-redirect" not in networks and not (EDGE_CELL_DIR / "nginx.json").exists(), "no UI"
    stated = re.search(r"^# Memory: (\d+) MB", (EDGE_CELL_DIR / "docker-compose.yml").read_text(), re.M)
    assert stated and int(stated.group(1)) == edge_stack.mem_limit_bytes(gateway["mem_limit"]) // 2**20


def test_cell_compose_is_a_gateway_only():
    """The cell: a gateway (and a demo robot) only; its name and Redis URL from cell.env."""
    compose = load(CELL_DIR / "docker-compose.yml")
    services = compose["services"]
    assert set(services) == {"gateway", "robot"}
    assert "demo" in services["robot"]["profiles"]
    gateway = services["gateway"]
    assert gateway["command"] == ["gateway"] and gateway["image"] == IMAGE and "mem_limit" in gateway
    assert gateway["env_file"] == ["cell.env"]
    assert not any(v.split(":")[0].endswith("-data") for v in gateway.get("volumes", [])), "no data volume"
    assert "environment" not in gateway, "all of its settings come from cell.env"
    example = env_lines(CELL_DIR / "env.example")
    assert {"LIFECYCLE_GATEWAY_NAME", "REDIS_URL", "LIFECYCLE_CHANNEL_PREFIX", "ROS_AUTOMATIC_DISCOVERY_RANGE",
            "ROS_STATIC_PEERS"} <= set(example)


def test_only_the_opt_in_file_gives_a_gateway_the_docker_socket():
    """The Docker Engine's socket (control of every container of the host) is mounted by the cell's
    opt-in file only, with the host's PID namespace, network and IPC it needs to find the nodes'
    containers; never by an Industrial Edge app (its rules allow bind mounts under ./ only)."""
    opt_in = "docker-compose.host-supervisor.yml"
    for path in ALL_COMPOSE:
        mounts = [v for service in (load(path).get("services") or {}).values() for v in service.get("volumes", [])
                  if "docker.sock" in str(v)]
        assert bool(mounts) == (path.name == opt_in), f"{path}: {mounts}"
    gateway = load(CELL_DIR / opt_in)["services"]["gateway"]
    assert (gateway["pid"], gateway["network_mode"], gateway["ipc"]) == ("host", "host", "host")
    assert gateway["environment"]["LIFECYCLE_DOCKER_SOCKET"] == "/var/run/docker.sock"
    assert gateway["env_file"] == ["cell.env"] and gateway["image"] == IMAGE


def test_redis_public_override():
    """Published only with a password for Redis's default user, taken from the environment."""
    override = load(DOCKER_DIR / "docker-compose.redis-public.yml")["services"]
    redis = override["redis"]
    assert re.fullmatch(r"\$\{REDIS_PASSWORD:\?[^}]*\}", redis["environment"]["REDIS_PASSWORD"])
    assert redis["ports"] and all(p.endswith(":6379") for p in redis["ports"])
    for name in ("web", "ingest", "gateway"):
        url = override[name]["environment"]["REDIS_URL"]
        assert re.fullmatch(r"redis://:\$\{REDIS_PASSWORD:\?[^}]*\}@redis:6379/0", url), f"{name}: {url}"


def test_plain_compose_takes_secrets_from_the_environment():
    compose = load(DOCKER_DIR / "docker-compose.yml")
    assert_site_roles(compose["services"], "plain")
    for service in compose["services"].values():
        assert service["image"] == IMAGE
        assert "mem_limit" in service
        for key, value in (service.get("environment") or {}).items():
            if "PASSWORD" in key or "SECRET" in key:
                assert re.fullmatch(r"\$\{%s:-\}" % key, str(value)), f"{key} must come from the env file"
    demo = {name for name, service in compose["services"].items() if "demo" in service.get("profiles", [])}
    assert {"robot-agv1", "robot-agv2"} <= demo


def test_nginx_json_is_a_websocket_capable_secure_redirect():
    entries = json.loads((EDGE_DIR / "nginx.json").read_text())
    assert set(entries) == {"web"}, "keyed by the compose service name"
    (entry,) = entries["web"]
    assert entry["name"] == "lifecycle" and entry["protocol"] == "HTTP" and entry["port"] == "8000"
    assert entry["rewriteTarget"] == "/"
    assert entry["isSecureRedirection"] is True
    headers = json.loads(entry["headers"])
    assert headers["proxy_set_header Upgrade"] == "$http_upgrade"
    assert headers["proxy_set_header Connection"] == "upgrade"
    # The prefix the device strips is the one the app is configured with.
    compose = load(EDGE_DIR / "docker-compose.yml")
    assert compose["services"]["web"]["environment"]["LIFECYCLE_URL_PREFIX"] == "/" + entry["name"]


def env_lines(path: Path) -> dict[str, str]:
    """KEY=VALUE lines of an env file (comments and blank lines skipped)."""
    pairs = {}
    for line in path.read_text().splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            key, sep, value = line.partition("=")
            assert sep, f"{path}: {line!r} is not KEY=VALUE"
            pairs[key.strip()] = value.strip()
    return pairs


SECRET_NAME = re.compile(r"PASSWORD|SECRET|TOKEN|PRIVATE|CREDENTIAL|API_KEY", re.I)
REFERENCE = re.compile(r"\$\{[A-Z_][A-Z0-9_]*(:?[-?][^}]*)?\}")  # ${NAME}, ${NAME:-default}, ${NAME:?message}
# A long run of letters and digits mixed, as generated passwords and tokens are (token_urlsafe, hex).
TOKEN_LIKE = re.compile(r"(?<![A-Za-z0-9_-])(?=[A-Za-z0-9_-]*\d)(?=[A-Za-z0-9_-]*[a-zA-Z])[A-Za-z0-9_-]{20,}")


def secret_problems(where: str, key: str, value: str) -> list[str]:
    """What in one setting looks like a secret written out (empty or a ${...} reference is fine)."""
    problems = []
    text = str(value if value is not None else "")
    literal = REFERENCE.sub("", text)
    if SECRET_NAME.search(key) and literal.strip():
        problems.append(f"{where}: {key} has a value written out")
    for url in re.findall(r"[a-z][a-z0-9+.-]*://\S+", text):
        password = urlsplit(url).password
        if password and not REFERENCE.fullmatch(password):
            problems.append(f"{where}: {key} holds a URL with a password")
    if TOKEN_LIKE.search(literal):
        problems.append(f"{where}: {key} holds something that looks like a token: {TOKEN_LIKE.search(literal)[0]!r}")
    return problems


def test_no_secret_values_in_compose_files_or_env_examples():
    """Every compose file and env example in docker/ (and the example app configuration):
    secrets are empty or ${...} references to the environment, never values."""
    assert len(ALL_COMPOSE) >= 5 and len(ALL_ENV_EXAMPLES) >= 2, (ALL_COMPOSE, ALL_ENV_EXAMPLES)
    problems = []
    for path in ALL_COMPOSE:
        for name, service in (load(path).get("services") or {}).items():
            environment = service.get("environment") or {}
            if isinstance(environment, list):
                environment = dict(item.partition("=")[::2] for item in environment)
            for key, value in environment.items():
                problems += secret_problems(f"{path.relative_to(DOCKER_DIR)} {name}", key, value)
            for word in service.get("command") or []:
                problems += secret_problems(f"{path.relative_to(DOCKER_DIR)} {name} command", "", word)
        # Anything else in the file (comments included): no URL with a password, no token.
        for number, line in enumerate(path.read_text().splitlines(), 1):
            problems += [p for p in secret_problems(f"{path.relative_to(DOCKER_DIR)}:{number}", "", line)
                         if "looks like a token" not in p or not line.lstrip().startswith("#")]
    for path in ALL_ENV_EXAMPLES:
        for key, value in env_lines(path).items():
            problems += secret_problems(str(path.relative_to(DOCKER_DIR)), key, value)
    config = json.loads((EDGE_DIR / "cfg-data" / "param.json").read_text())
    assert config["admin"]["password"] == "", "the example app configuration has no password"
    config = json.loads((EDGE_CELL_DIR / "cfg-data" / "param.json").read_text())
    assert config["redis"] == {"url": "", "username": "", "password": "", "caCertificate": ""}, config["redis"]
    assert not problems, "\n".join(problems)
    # The checks themselves catch what they are for.
    assert secret_problems("x", "REDIS_PASSWORD", "hunter2-but-longer")
    assert secret_problems("x", "REDIS_URL", "redis://gw-a:s3cr3t@redis:6379/0")
    assert secret_problems("x", "OTHER", "Jx8Vd0Pq3mZ7tK2wLr9sY4bN")
    assert not secret_problems("x", "REDIS_URL", "redis://:${REDIS_PASSWORD:?set it}@redis:6379/0")
    assert not secret_problems("x", "DJANGO_SUPERUSER_PASSWORD", "${DJANGO_SUPERUSER_PASSWORD:-}")


def test_one_version_everywhere():
    assert re.fullmatch(r"\d+\.\d+\.\d+", VERSION)
    for path in [DOCKER_DIR / "docker-compose.yml", *COMPOSE_FILES["edge+demo"], *COMPOSE_FILES["edge-no-layer2+demo"],
                 CELL_DIR / "docker-compose.yml", EDGE_CELL_DIR / "docker-compose.yml"]:
        images = set(re.findall(r"^\s*image:\s*(\S+)", path.read_text(), re.M))
        assert images == {IMAGE}, f"{path.name}: {images}"
