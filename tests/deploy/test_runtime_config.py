"""The app configuration (cfg-data): the JSON-Forms templates the Industrial Edge Management
fills in, and docker/runtime/config.py turning a configuration into the containers' environment
(run as the entrypoint runs it, as a script with this Python: no Docker needed)."""
from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
from urllib.parse import urlsplit

import pytest

from tests.deploy.engine import DOCKER_DIR, EDGE_DIR

EDGE_CELL_DIR = DOCKER_DIR / "edge-cell"


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


TEMPLATES = {
    "edge": (EDGE_DIR, ("admin", "site", "ros")),
    "edge-cell": (EDGE_CELL_DIR, ("gateway", "redis", "ros")),
}


@pytest.mark.parametrize("app", list(TEMPLATES))
def test_configuration_template_is_json_forms(app, tmp_path):
    """Valid JSON, dataschema + uischema, every field of the schema in the form and every
    control naming a field; the example configuration is accepted by the entrypoint."""
    folder, parts = TEMPLATES[app]
    template = json.loads((folder / "cfg-data-template" / "param.json").read_text())
    example = json.loads((folder / "cfg-data" / "param.json").read_text())
    assert set(template) == {"dataschema", "uischema"}
    schema, ui = template["dataschema"], template["uischema"]
    assert set(example) == set(schema["properties"]), "the example has the template's parts"
    for part in parts:
        assert set(example[part]) == set(schema["properties"][part]["properties"]), part
    role = "gateway" if app == "edge-cell" else "web"
    result = run_config("env", role, config=example, tmp_path=tmp_path)
    assert result.returncode == 0, result.stderr
    seen = set()
    for scope, element in _scopes(ui):
        target = _resolve(schema, scope)  # KeyError: the form names a field that does not exist
        seen.add(scope)
        detail = element.get("options", {}).get("detail")
        if detail:
            for inner, _ in _scopes(detail):
                _resolve(target["items"], inner)
    for part in parts:
        for field in schema["properties"][part]["properties"]:
            assert f"#/properties/{part}/properties/{field}" in seen, f"{part}.{field} is not in the form"
    if app == "edge":
        assert "#/properties/robots" in seen
        robot = schema["properties"]["robots"]["items"]
        assert set(robot["required"]) == {"name", "domainId"}
    else:
        assert schema["required"] == ["gateway", "redis"] and example["redis"]["password"] == ""
        secret = _resolve(schema, "#/properties/redis/properties/password")
        assert secret.get("default", "") == "", "no password in the template"
        password_control = next(e for s, e in _scopes(ui) if s.endswith("/redis/properties/password"))
        assert password_control.get("options", {}).get("format") == "password"


def run_config(*args, config: dict | None, tmp_path, env: dict | None = None):
    """docker/runtime/config.py with this configuration file (a missing one when None)."""
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
    # A discovery server: the gateway a super client unless told otherwise.
    servers = {"ros": {"discoveryServer": "10.1.2.1:11811;;dds.plant.local:11811"}}
    env = exported(run_config("env", config=servers, tmp_path=tmp_path).stdout)
    assert env["ROS_DISCOVERY_SERVER"] == "10.1.2.1:11811;;dds.plant.local:11811" and env["ROS_SUPER_CLIENT"] == "TRUE"
    servers["ros"]["superClient"] = False
    assert exported(run_config("env", config=servers, tmp_path=tmp_path).stdout)["ROS_SUPER_CLIENT"] == "FALSE"
    # No allowed hosts anywhere: any host, with a warning in the log.
    result = run_config("env", config=None, tmp_path=tmp_path)
    assert exported(result.stdout) == {"DJANGO_ALLOWED_HOSTS": "*"} and "WARNING" in result.stderr


def test_gateway_configuration_becomes_environment(tmp_path):
    """A cell's gateway (docker/edge-cell/): name, Redis URL with its credentials, key prefix
    from cfg-data, for the gateway role only (a site's web never follows a gateway's Redis)."""
    whole = {"gateway": {"name": "cell-a", "channelPrefix": "lifecycle", "logLevel": "debug"},
             "redis": {"url": "redis://gw-cell-a:Pw_0-x@site.plant.local:6379/0"}}
    result = run_config("env", "gateway", config=whole, tmp_path=tmp_path)
    assert result.returncode == 0, result.stderr
    assert exported(result.stdout) == {
        "LIFECYCLE_GATEWAY_NAME": "cell-a", "LIFECYCLE_CHANNEL_PREFIX": "lifecycle", "LIFECYCLE_LOG_LEVEL": "DEBUG",
        "REDIS_URL": "redis://gw-cell-a:Pw_0-x@site.plant.local:6379/0", "DJANGO_ALLOWED_HOSTS": "*",
    }
    assert "Pw_0-x" not in result.stderr
    for role in ("web", "ingest"):
        assert "REDIS_URL" not in exported(run_config("env", role, config=whole, tmp_path=tmp_path).stdout)
    # User and password apart (characters a URL must escape), TLS with a private CA.
    ca = "-----BEGIN CERTIFICATE-----\nMIIB\n-----END CERTIFICATE-----"
    split = {"gateway": {"name": "cell-a"},
             "redis": {"url": "rediss://site.plant.local:6380/0", "username": "gw-cell-a", "password": "p@ss:w/rd",
                       "caCertificate": ca}}
    ca_file = tmp_path / "ca.crt"
    result = run_config("env", "gateway", config=split, tmp_path=tmp_path,
                        env={"LIFECYCLE_REDIS_CA_FILE": str(ca_file)})
    assert result.returncode == 0, result.stderr
    url = exported(result.stdout)["REDIS_URL"]
    assert url == f"rediss://gw-cell-a:p%40ss%3Aw%2Frd@site.plant.local:6380/0?ssl_ca_certs={ca_file}", url
    assert urlsplit(url).password == "p%40ss%3Aw%2Frd" and ca_file.read_text().startswith("-----BEGIN")


@pytest.mark.parametrize(
    "config, message",
    [
        ({"gateway": {"name": "Cell A"}}, "gateway.name"),
        ({"redis": {"url": "redis://gw-cell-a:x@site:6379/0"}}, "gateway.name is missing"),
        ({"gateway": {"name": "cell-b"}, "redis": {"url": "redis://gw-cell-a:x@site:6379/0"}}, "belongs to"),
        ({"gateway": {"name": "cell-a"}, "redis": {"url": "redis://site:6379/0"}}, "no password"),
        ({"gateway": {"name": "cell-a"}, "redis": {"url": "site:6379"}}, "redis.url must look like"),
        ({"gateway": {"name": "cell-a"}, "redis": {"username": "gw-cell-a", "password": "x"}}, "redis.url is missing"),
        ({"gateway": {"name": "cell-a"}, "redis": {"url": "redis://gw-cell-a:x@site/0", "caCertificate": "-----BEGIN"}},
         "rediss://"),
        ({"gateway": {"name": "cell-a"}, "redis": "redis://site"}, "'redis' must be an object"),
        ({"gateway": {"name": "cell-a", "channelPrefix": "a b"}}, "channelPrefix"),
    ],
)
def test_bad_gateway_configuration_is_refused_with_a_reason(config, message, tmp_path):
    result = run_config("env", "gateway", config=config, tmp_path=tmp_path)
    assert result.returncode == 78 and message in result.stderr, result.stderr


@pytest.mark.parametrize(
    "config, message",
    [
        ({"ros": {"discoveryServer": "10.1.2.1:99999"}}, "ros.discoveryServer"),
        ({"ros": {"discoveryServer": "10.1.2.1:11811", "superClient": "yes"}}, "ros.superClient"),
        ({"ros": {"staticPeers": "10.1.2.3;robot 4"}}, "ros.staticPeers"),
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
