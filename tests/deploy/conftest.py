"""Fixtures of the deploy tests (`make test-deploy`): a real Docker engine, the images built
offline, and the Industrial Edge compose file running behind an nginx set up like the device's,
its gateway on a stand-in for the device's layer-2 network with a robot on the plant LAN.

Nothing is skipped: where Docker cannot run, the tests fail and say why. Whatever the tests
start (dockerd, the compose project, the proxy-redirect network, nginx, the plant LAN's
namespace, veth, macvlan network and robot) they also stop.
The base image and the wheelhouse stay cached on this machine (Docker's image store and
~/.cache/lifecycle-manager), so a second run, even from a fresh clone, builds in seconds.
"""
from __future__ import annotations

import json
import os
import secrets
import shutil
import tempfile
import time
from pathlib import Path

import pytest

from tests import domains
from tests.deploy import edge_stack, engine, layer2
from tests.deploy.edge_stack import Stack
from tests.deploy.engine import DEMO_DOMAIN, DEMO_ROBOT, EDGE_DIR, PLANT_DOMAIN, PLANT_ROBOT


def pytest_configure(config) -> None:
    config.addinivalue_line("markers", "deploy: real Docker engine, images and the Industrial Edge stack")


def pytest_collection_modifyitems(items) -> None:
    for item in items:
        if "/deploy/" in str(item.fspath):
            item.add_marker(pytest.mark.deploy)


_TIMINGS = engine.Timings()


def pytest_sessionstart(session) -> None:
    _TIMINGS.record("session_start", time.time())


def pytest_terminal_summary(terminalreporter) -> None:
    values = dict(_TIMINGS.values)
    if "session_start" not in values or len(values) == 1:
        return
    values["session_s"] = round(time.time() - values.pop("session_start"), 1)
    _TIMINGS.values = values
    _TIMINGS.save()
    terminalreporter.section("deploy figures")
    for name, value in values.items():
        terminalreporter.write_line(f"{name}: {value}")


@pytest.fixture(scope="session")
def timings() -> engine.Timings:
    return _TIMINGS


@pytest.fixture(scope="session")
def scratch():
    path = Path(tempfile.mkdtemp(prefix="lifecycle-deploy-"))
    yield path
    shutil.rmtree(path, ignore_errors=True)


@pytest.fixture(scope="session")
def docker_engine(scratch, timings):
    """A Docker daemon that answers: the running one, or one started here (and stopped at the end)."""
    with timings.timed("tools_install_s"):
        installed = engine.ensure_tools()
    timings.record("tools_installed", installed)
    with timings.timed("dockerd_start_s"):
        daemon = engine.Daemon.ensure(scratch / "dockerd")
    timings.record("dockerd_started_by_tests", daemon.started_here)
    yield daemon
    daemon.stop()
    if daemon.started_here:
        assert daemon.process.poll() is not None, "dockerd did not stop"


@pytest.fixture(scope="session")
def image(docker_engine, timings) -> str:
    return engine.build_images(timings)


@pytest.fixture(scope="session")
def stack(image, scratch, timings):
    """The edge compose file plus a demo robot container, as a device runs them, with the
    web service published on a loopback port (test-only override) for the nginx in front.
    Its gateway joins the layer-2 network: first the app is shown not to start without it
    (``extra["without_layer2"]``), then a plant LAN stand-in is made (``extra["plant"]``) with
    a robot process in it, registered in cfg-data as the device's operator would."""
    workdir = scratch / "app"
    (workdir / "cfg-data").mkdir(parents=True)
    for name in ("docker-compose.yml", "docker-compose.demo.yml"):
        shutil.copy(EDGE_DIR / name, workdir / name)
    password = "deploy-" + secrets.token_urlsafe(16)
    config = {
        "admin": {"username": "admin", "password": password},
        "site": {"allowedHosts": "127.0.0.1,localhost", "urlPrefix": "/lifecycle", "behindTlsProxy": True},
        "ros": {"discoveryRange": "SUBNET"},
        "robots": [{"name": DEMO_ROBOT, "domainId": DEMO_DOMAIN}, {"name": PLANT_ROBOT, "domainId": PLANT_DOMAIN}],
    }
    (workdir / "cfg-data" / "param.json").write_text(json.dumps(config, indent=2))
    web_port = engine.free_port()
    # The device's nginx reaches "web" over proxy-redirect; the nginx of this test runs on the
    # host, so "web" is published on a loopback port (no host networking, nothing off-machine).
    (workdir / "docker-compose.test.yml").write_text(
        f"version: '2.4'\nservices:\n  web:\n    ports: [\"127.0.0.1:{web_port}:8000\"]\n"
    )
    stack = Stack(
        project=f"lcdeploy{os.getpid()}",
        workdir=workdir,
        files=["docker-compose.yml", "docker-compose.demo.yml", "docker-compose.test.yml"],
        web_port=web_port,
        admin_password=password,
    )
    timings.record("stale_projects_removed", edge_stack.remove_stale_projects())
    timings.record("stale_plant_lans_removed", layer2.remove_stale())
    domains.claim([PLANT_DOMAIN])  # the sniffer tells its packets by port: no other run in it
    plant = layer2.PlantLan("a", label=f"lcdeploy{os.getpid()}plant", log_dir=scratch / "plant-a")
    stack.extra["plant"] = plant
    networks = engine.run(["docker", "network", "ls", "--format", "{{.Name}}"], timeout=30).stdout.split()
    if layer2.NETWORK in networks:
        raise engine.DeployError(f"a Docker network {layer2.NETWORK} exists already; the tests make their own")
    if "proxy-redirect" not in networks:  # as the Industrial Edge runtime has it
        engine.run(["docker", "network", "create", "proxy-redirect"], timeout=60)
        stack.created_network = True
    try:
        # A device without layer-2 access: the app is refused before any container exists.
        refused = stack.compose("up", "--no-start", timeout=120, check=False)
        stack.extra["without_layer2"] = (refused.returncode, refused.stdout + refused.stderr,
                                         stack.leftovers())
        stack.down_by_label()
        with timings.timed("plant_lan_up_s"):
            plant.create()
            plant.robot(PLANT_ROBOT, PLANT_DOMAIN)
        with timings.timed("stack_up_s"):
            stack.compose("up", "-d", timeout=300)
            engine.wait_for(lambda: stack.health("web") == "healthy", 120, "the web container to be healthy")
        stack.proxy_port = engine.free_port()
        stack.nginx = edge_stack.start_nginx(scratch / "nginx", stack.proxy_port, web_port)
        yield stack
    finally:
        edge_stack.stop_process(stack.nginx)
        stack.save_logs()
        with timings.timed("stack_down_s"):
            stack.down()
            plant.close()
        domains.release([PLANT_DOMAIN])
        left = stack.leftovers()
        assert not left, f"compose project {stack.project} left {left} (see tests/artifacts/deploy/compose-down.log)"
        left = plant.leftovers()
        assert not left, f"the plant LAN stand-in left {left}"
