"""The deployment files themselves: compose files valid for docker-compose (format 2.4), the
Industrial Edge rules kept, the reverse-proxy entry, the configuration template."""
from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys

import pytest
import yaml

from tests.deploy import edge_stack, engine
from tests.deploy.engine import DOCKER_DIR, EDGE_DIR, IMAGE, VERSION

COMPOSE_FILES = {
    "plain": [DOCKER_DIR / "docker-compose.yml"],
    "edge": [EDGE_DIR / "docker-compose.yml"],
    "edge+demo": [EDGE_DIR / "docker-compose.yml", EDGE_DIR / "docker-compose.demo.yml"],
}
APP_MEMORY_BUDGET = 500 * 1024**2  # the thesis' single container had 500 MB; the whole app fits in it


def load(path):
    return yaml.safe_load(path.read_text())


@pytest.mark.parametrize("name", list(COMPOSE_FILES))
def test_compose_file_validates(name, docker_engine):
    """`docker-compose config` accepts the file (it rejects unknown keys and bad values)."""
    argv = ["docker-compose"]
    for path in COMPOSE_FILES[name]:
        argv += ["-f", str(path)]
    if name == "plain":
        argv += ["--profile", "demo"]
    engine.run(argv + ["config", "-q"], timeout=60, cwd=COMPOSE_FILES[name][0].parent)


@pytest.mark.parametrize("path", [EDGE_DIR / "docker-compose.yml", EDGE_DIR / "docker-compose.demo.yml"])
def test_edge_compose_follows_industrial_edge_rules(path):
    compose = load(path)
    assert str(compose["version"]) == "2.4"
    for name, service in compose["services"].items():
        where = f"{path.name}: service {name}"
        assert service["image"] == IMAGE, f"{where}: image must be {IMAGE} (docker/VERSION)"
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


def test_edge_app_layout():
    compose = load(EDGE_DIR / "docker-compose.yml")
    services, networks = compose["services"], compose["networks"]
    assert networks["proxy-redirect"] == {"external": True}
    assert "proxy-redirect" in services["web"]["networks"]
    assert all("proxy-redirect" not in s.get("networks", []) for n, s in services.items() if n != "web")
    assert networks["lifecycle"].get("internal") is True, "the app's own services talk on an internal network"
    assert "redis" in [n for n in services if "lifecycle" in services[n]["networks"]]
    for name in ("web", "gateway"):
        assert "./cfg-data/:/cfg-data/:ro" in services[name]["volumes"]
        assert any(v.startswith("lifecycle-data:") for v in services[name]["volumes"])
    assert "lifecycle-data" in compose["volumes"]
    total = sum(edge_stack.mem_limit_bytes(s["mem_limit"]) for s in services.values())
    assert total <= APP_MEMORY_BUDGET, f"the app's memory limits add up to {total / 2**20:.0f} MiB"
    for name, service in services.items():
        keys = " ".join(service.get("environment", {})).upper()
        assert "PASSWORD" not in keys and "SECRET" not in keys, f"{name}: secrets belong in cfg-data"


def test_plain_compose_takes_secrets_from_the_environment():
    compose = load(DOCKER_DIR / "docker-compose.yml")
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


def _scopes(element):
    if "scope" in element:
        yield element["scope"], element
    for child in element.get("elements", []):
        yield from _scopes(child)


def _resolve(schema: dict, scope: str) -> dict:
    node = schema
    for part in scope.lstrip("#/").split("/"):
        node = node[part]
    return node


def test_configuration_template_is_json_forms():
    template = json.loads((EDGE_DIR / "cfg-data-template" / "param.json").read_text())
    assert set(template) == {"dataschema", "uischema"}
    schema, ui = template["dataschema"], template["uischema"]
    seen = set()
    for scope, element in _scopes(ui):
        target = _resolve(schema, scope)  # KeyError: the form names a field that does not exist
        seen.add(scope)
        detail = element.get("options", {}).get("detail")
        if detail:
            for inner, _ in _scopes(detail):
                _resolve(target["items"], inner)
    for part in ("admin", "site", "ros"):
        for field in schema["properties"][part]["properties"]:
            assert f"#/properties/{part}/properties/{field}" in seen, f"{part}.{field} is not in the form"
    assert "#/properties/robots" in seen
    robot = schema["properties"]["robots"]["items"]
    assert set(robot["required"]) == {"name", "domainId"}


def run_config(*args, config: dict | None, tmp_path, env: dict | None = None):
    path = tmp_path / ("param.json" if config is not None else "absent.json")
    if config is not None:
        path.write_text(json.dumps(config))
    environment = {k: v for k, v in os.environ.items() if not k.startswith(("DJANGO_", "LIFECYCLE_", "ROS_"))}
    environment.update(LIFECYCLE_CONFIG_FILE=str(path), **(env or {}))
    return subprocess.run(
        [sys.executable, str(DOCKER_DIR / "runtime" / "config.py"), *args],
        capture_output=True, text=True, timeout=60, env=environment,
    )


def exported(script: str) -> dict[str, str]:
    """The variables a shell would get from `eval` of the printed export lines."""
    env = {}
    for line in script.splitlines():
        words = shlex.split(line)
        assert words[0] == "export" and len(words) == 2, line
        name, _, value = words[1].partition("=")
        env[name] = value
    return env


def test_configuration_becomes_environment(tmp_path):
    """What the entrypoint evaluates: cfg-data settings as shell exports (values quoted)."""
    example = json.loads((EDGE_DIR / "cfg-data" / "param.json").read_text())
    assert run_config("env", config=example, tmp_path=tmp_path).returncode == 0
    config = {
        "site": {"allowedHosts": "ied-1.plant.local, 10.0.0.5", "urlPrefix": "/lifecycle/", "behindTlsProxy": True,
                 "logLevel": "warning"},
        "ros": {"discoveryRange": "subnet", "staticPeers": "192.168.5.20;192.168.5.21", "serviceTimeout": 4},
        "robots": [{"name": "agv-1", "domainId": 21}],
    }
    result = run_config("env", config=config, tmp_path=tmp_path)
    assert result.returncode == 0, result.stderr
    env = exported(result.stdout)
    assert env == {
        "DJANGO_ALLOWED_HOSTS": "ied-1.plant.local,10.0.0.5",
        "LIFECYCLE_URL_PREFIX": "/lifecycle",
        "LIFECYCLE_BEHIND_TLS_PROXY": "1",
        "LIFECYCLE_LOG_LEVEL": "WARNING",
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET",
        "ROS_STATIC_PEERS": "192.168.5.20;192.168.5.21",
        "LIFECYCLE_SERVICE_TIMEOUT": "4.0",
    }
    # No allowed hosts anywhere: any host, with a warning in the log.
    result = run_config("env", config=None, tmp_path=tmp_path)
    assert exported(result.stdout) == {"DJANGO_ALLOWED_HOSTS": "*"} and "WARNING" in result.stderr


@pytest.mark.parametrize(
    "config, message",
    [
        ({"site": {"urlPrefix": "lifecycle"}}, "urlPrefix"),
        ({"ros": {"discoveryRange": "EVERYWHERE"}}, "discoveryRange"),
        ({"robots": [{"name": "agv-1"}]}, "robots[0]"),
        ({"robots": "agv-1"}, "'robots' must be a list"),
        ({"site": {"allowedHosts": "x"}, "admin": "root"}, "'admin' must be an object"),
    ],
)
def test_bad_configuration_is_refused_with_a_reason(config, message, tmp_path):
    result = run_config("env", config=config, tmp_path=tmp_path)
    assert result.returncode == 78 and message in result.stderr, result.stderr


def test_one_version_everywhere():
    assert re.fullmatch(r"\d+\.\d+\.\d+", VERSION)
    for path in [DOCKER_DIR / "docker-compose.yml", *COMPOSE_FILES["edge+demo"]]:
        images = set(re.findall(r"^\s*image:\s*(\S+)", path.read_text(), re.M))
        assert images == {IMAGE}, f"{path.name}: {images}"
