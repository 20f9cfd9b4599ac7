"""The image built offline, and the Industrial Edge app running for real: web, ingest, the
gateway "local" and redis, plus a demo robot container, behind an nginx that serves it under
/lifecycle/ as the device does."""
from __future__ import annotations

import json
import re
import time

import pytest

from tests.deploy import edge_stack, engine
from tests.deploy.client import Browser, insecure_context
from tests.deploy.engine import DEMO_ROBOT, DOCKER_DIR, EDGE_DIR, IMAGE, PLANT_ROBOT, VERSION

PREFIX = "/lifecycle"
# The lifecycle nodes of the demo robot container (its joystick is a plain node).
NODES = ("joy_to_vel", "lidar_driver", "camera_driver", "planner")
# A state label on its own: "active" but not the end of "inactive".
ACTIVE = re.compile(r"(?<![A-Za-z])active(?![A-Za-z])")


def inspect(image: str) -> dict:
    return json.loads(engine.run(["docker", "image", "inspect", image], timeout=30).stdout)[0]


def test_image_built_offline(image):
    """docker/build-images.sh built it with `docker build --network none` from the wheelhouse."""
    assert image == IMAGE
    log = (engine.ARTIFACTS / "build-images.log").read_text()
    assert re.search(r"docker build --network none", (DOCKER_DIR / "build-images.sh").read_text())
    assert "Successfully tagged " + IMAGE in log or "naming to docker.io/library/" + IMAGE in log, log[-2000:]
    details = inspect(image)
    config = details["Config"]
    assert config["User"] == "10001:10001", "runs as an unprivileged user"
    assert config["Healthcheck"]["Test"][0] == "CMD"
    assert config["Labels"]["org.opencontainers.image.version"] == VERSION
    env = dict(item.split("=", 1) for item in config["Env"])
    assert not any("SECRET" in k or "PASSWORD" in k for k in env), env
    # With --network none any download would fail the build; pip is told so as well.
    assert "pip install --no-index --find-links /tmp/wheelhouse" in (DOCKER_DIR / "Dockerfile").read_text()
    # Runs without any network; static files are in the image; no secret key was written into it.
    probe = engine.run(
        ["docker", "run", "--rm", "--network", "none", "--entrypoint", "sh", image, "-c",
         "python -c 'import rclpy, rclpy.lifecycle, django, daphne, channels_redis, whitenoise' && "
         "test -f /opt/lifecycle/staticfiles/css/site.css && ! ls /data/secret_key 2>/dev/null && id -u"],
        timeout=120,
    )
    assert probe.stdout.strip() == "10001"


def test_package_for_the_publisher(image, scratch, timings):
    out = scratch / "package"
    with timings.timed("package_s"):
        engine.run([str(EDGE_DIR / "package.sh"), "--no-build", "--output", str(out)], timeout=600)
    files = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()}
    tarball = f"images/lifecycle-manager_{VERSION}.tar"
    assert {"docker-compose.yml", "docker-compose.demo.yml", "nginx.json", "README.md", "SHA256SUMS",
            "cfg-data/param.json", "cfg-data-template/param.json", tarball} <= files
    manifest = engine.run(["tar", "-xOf", str(out / tarball), "manifest.json"], timeout=120).stdout
    assert json.loads(manifest)[0]["RepoTags"] == [IMAGE]
    readme = (out / "README.md").read_text()
    assert "iectl" in readme and "docker load" in readme and "JSON schema" in readme
    assert (out.parent / "package.tar.gz").exists()
    assert "docker-compose.no-layer2.yml" in files and "zzz_layer2_net1" in readme
    timings.record("package_mb", round(sum(p.stat().st_size for p in out.rglob("*") if p.is_file()) / 1e6))


def test_package_of_a_cells_gateway(image, scratch):
    """package.sh --app edge-cell: the gateway-only app, no reverse-proxy entry."""
    out = scratch / "package-cell"
    engine.run([str(EDGE_DIR / "package.sh"), "--app", "edge-cell", "--no-build", "--output", str(out)], timeout=600)
    files = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()}
    assert files == {"docker-compose.yml", "README.md", "SHA256SUMS", "cfg-data/param.json",
                     "cfg-data-template/param.json", f"images/lifecycle-manager_{VERSION}.tar"}, files
    assert (out / "docker-compose.yml").read_text() == (DOCKER_DIR / "edge-cell" / "docker-compose.yml").read_text()
    readme = (out / "README.md").read_text()
    assert "add_gateway" in readme and "zzz_layer2_net1" in readme and "Memory limit: 192 MB" in readme
    assert (out.parent / "package-cell.tar.gz").exists()


# ---------------------------------------------------------------------------------------
# Through the proxy


@pytest.fixture(scope="module")
def browser(stack) -> Browser:
    return Browser("127.0.0.1", stack.proxy_port)


@pytest.fixture(scope="module")
def logged_in(stack, browser) -> Browser:
    response = browser.login(PREFIX, "admin", stack.admin_password)
    assert response.status == 302, f"login failed: {response}"
    assert response.headers["Location"] in (f"{PREFIX}/", f"https://127.0.0.1:{stack.proxy_port}{PREFIX}/")
    assert "sessionid" in browser.cookies
    return browser


@pytest.fixture(scope="module")
def token(stack) -> str:
    value = stack.manage("create_api_token", "admin", "--name", "deploy test")
    assert re.fullmatch(r"\S{20,}", value), value
    return value


def node_list(browser: Browser) -> dict[str, dict]:
    response = browser.get(f"{PREFIX}/api/v1/nodes", headers={"Accept": "application/json"})
    assert response.status == 200, response
    return {node["id"]: node for node in response.json()["nodes"]}


def wait_nodes_alive(browser: Browser, timeout: float = 90) -> dict[str, dict]:
    wanted = {f"{DEMO_ROBOT}.{name}" for name in NODES}

    def ready():
        nodes = node_list(browser)
        return nodes if all(nodes.get(key, {}).get("alive") for key in wanted) else None

    return engine.wait_for(ready, timeout, f"the demo robot's nodes {sorted(wanted)} to be listed alive", interval=1)


def transition(browser: Browser, token: str, key: str, name: str, timeout: float = 30):
    """POST a transition with the bearer token; retried while the gateway (re)starts."""

    def attempt():
        response = browser.api("POST", f"{PREFIX}/api/v1/nodes/{key}/transition", token, {"transition": name})
        if response.status in (409, 502, 503) and response.json()["error"]["code"] in (
            "gateway_offline", "node_offline"
        ):
            return None
        return response

    response = engine.wait_for(attempt, timeout, f"{name} of {key} to be accepted", interval=1)
    assert response.status == 200 and response.json()["success"], f"{name} of {key}: {response}"
    return response.json()


def bring_to(browser: Browser, token: str, key: str, goal: str) -> None:
    path = {"unconfigured": ["configure", "activate"], "inactive": ["activate"], "active": []}
    if goal == "inactive":
        path = {"unconfigured": ["configure"], "inactive": [], "active": ["deactivate"]}
    state = node_list(browser)[key]["state"]["label"]
    for step in path[state]:
        transition(browser, token, key, step)


def test_site_served_under_the_prefix(stack, browser):
    """nginx strips /lifecycle/; every link the app sends carries it again."""
    response = browser.get(f"{PREFIX}/", cookies=False)
    assert response.status == 302 and response.headers["Location"].startswith(f"{PREFIX}/login/"), response
    page = browser.get(f"{PREFIX}/login/", cookies=False)
    assert page.status == 200
    assert f'action="{PREFIX}/login/"' in page.text
    stylesheet = re.search(r'<link rel="stylesheet" href="([^"]+)"', page.text).group(1)
    assert stylesheet.startswith(f"{PREFIX}/static/"), stylesheet
    asset = browser.get(stylesheet, cookies=False)
    assert asset.status == 200 and b"{" in asset.body, "static files are served by the app (WhiteNoise)"
    assert browser.get(PREFIX, cookies=False).status == 301  # /lifecycle -> /lifecycle/, as on the device
    german = browser.get(f"{PREFIX}/login/", cookies=False, headers={"Accept-Language": "de-DE,de;q=0.9"})
    assert '<html lang="de">' in german.text and "<h1>Anmelden</h1>" in german.text, "the image has the catalogue"


def test_login_through_the_proxy(stack, logged_in):
    page = logged_in.get(f"{PREFIX}/")
    assert page.status == 200, page
    assert "Log in" not in page.text.split("<h1", 1)[-1][:200]


def test_demo_robot_nodes_listed(logged_in):
    """The gateway container finds the robot container's lifecycle nodes over DDS (compose network)."""
    nodes = wait_nodes_alive(logged_in)
    robots = {n["robot"] for n in nodes.values()}
    assert DEMO_ROBOT in robots and robots <= {DEMO_ROBOT, PLANT_ROBOT}, robots


def test_site_processes_and_the_gateway_local(stack, logged_in):
    """ingest holds its lease, the gateway "local" (of the robots from cfg-data) beats: both
    healthy by their Redis checks; the gateway container has no database and no data volume."""
    for service in ("ingest", "gateway", "redis"):
        engine.wait_for(lambda s=service: stack.health(s) == "healthy", 120, f"{service} to be healthy")

    def local_online():
        response = logged_in.get(f"{PREFIX}/api/v1/gateways", headers={"Accept": "application/json"})
        assert response.status == 200, response
        gateways = {g["name"]: g for g in response.json()["gateways"]}
        return gateways if gateways.get("local", {}).get("online") else None

    gateways = engine.wait_for(local_online, 60, "gateway local online in /api/v1/gateways", interval=1)
    assert set(gateways) == {"local"} and gateways["local"]["robots"] == sorted([DEMO_ROBOT, PLANT_ROBOT]), gateways
    gateway = stack.container("gateway")
    mounts = json.loads(engine.run(["docker", "inspect", "-f", "{{json .Mounts}}", gateway], timeout=30).stdout)
    assert [m["Destination"] for m in mounts] == ["/cfg-data"], f"the gateway mounts only cfg-data: {mounts}"
    no_database = "test ! -e /data/db.sqlite3 && test ! -e /tmp/gateway/db.sqlite3"
    engine.run(["docker", "exec", gateway, "sh", "-c", no_database], timeout=30)
    logs = stack.compose("logs", "--no-color", "ingest", timeout=60).stdout
    assert "holding the ingest lease" in logs, logs[-2000:]


def test_transition_from_the_web_container(stack, logged_in, token):
    """`manage.py lifecycle set` run inside the web container: through Redis to the gateway
    container, and its audit record (source cli) is there when the command returns."""
    wait_nodes_alive(logged_in)
    key = f"{DEMO_ROBOT}.joy_to_vel"
    state = node_list(logged_in)[key]["state"]["label"]
    step = {"unconfigured": "configure", "inactive": "activate", "active": "deactivate"}[state]
    output = stack.manage("lifecycle", "set", key, step, "--user", "admin")
    assert output == "Transitioning successful", output
    records = logged_in.api("GET", f"{PREFIX}/api/v1/transitions?node={key}", token).json()["transitions"]
    assert records and records[0]["source"] == "cli" and records[0]["outcome"] == "succeeded", records[:1]
    assert records[0]["transition"]["label"] == step


def test_activate_a_node_with_the_json_api(logged_in, token):
    wait_nodes_alive(logged_in)
    key = f"{DEMO_ROBOT}.lidar_driver"
    bring_to(logged_in, token, key, "inactive")
    result = transition(logged_in, token, key, "activate")
    assert result["to"]["label"] == "active", result
    assert node_list(logged_in)[key]["state"]["label"] == "active"
    records = logged_in.api("GET", f"{PREFIX}/api/v1/transitions?node={key}", token).json()["transitions"]
    assert records and records[0]["outcome"] == "succeeded" and records[0]["source"] == "api", records[:1]


def test_state_change_arrives_over_the_websocket(stack, logged_in, token):
    """The live-update socket (ws/fleet/ under the prefix, session cookie, Origin checked)
    pushes the node's new state when the JSON API changes it."""
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    wait_nodes_alive(logged_in)
    key = f"{DEMO_ROBOT}.camera_driver"
    bring_to(logged_in, token, key, "inactive")
    url = f"wss://127.0.0.1:{stack.proxy_port}{PREFIX}/ws/fleet/"
    try:
        socket = connect(
            url, ssl=insecure_context(), origin=logged_in.origin, open_timeout=15,
            additional_headers={"Cookie": logged_in.cookie_header()},
        )
    except InvalidStatus as exc:
        pytest.fail(f"the WebSocket endpoint {url} refused the handshake: HTTP {exc.response.status_code}")
    received: list[str] = []
    with socket:
        transition(logged_in, token, key, "activate")
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            try:
                message = socket.recv(timeout=max(deadline - time.monotonic(), 0.1))
            except TimeoutError:
                break
            text = message if isinstance(message, str) else message.decode(errors="replace")
            received.append(text)
            if key in text and ACTIVE.search(text):
                break
    assert any(key in text and ACTIVE.search(text) for text in received), (
        f"no message naming {key} as active within 20 s; got {len(received)}: {[t[:200] for t in received[-5:]]}"
    )


def test_websocket_refuses_a_foreign_origin(stack, logged_in):
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    url = f"wss://127.0.0.1:{stack.proxy_port}{PREFIX}/ws/fleet/"
    with pytest.raises(InvalidStatus) as refused:
        with connect(url, ssl=insecure_context(), origin="https://evil.example", open_timeout=15,
                     additional_headers={"Cookie": logged_in.cookie_header()}):
            pass
    assert refused.value.response.status_code == 403


def test_memory_within_limits(stack, timings):
    """Every container under its mem_limit (which Docker enforces: the limit shows in stats)."""
    compose = edge_stack.yaml_services(EDGE_DIR / "docker-compose.yml", EDGE_DIR / "docker-compose.demo.yml")
    ids = {service: stack.container(service) for service in compose}
    stats = engine.run(
        ["docker", "stats", "--no-stream", "--format", "{{.ID}}\t{{.MemUsage}}", *ids.values()], timeout=60
    ).stdout
    usage = {}
    for line in stats.strip().splitlines():
        cid, mem = line.split("\t")
        used, limit = (edge_stack.stats_bytes(part) for part in mem.split("/"))
        service = next(s for s, full in ids.items() if full.startswith(cid))
        usage[service] = round(used / 2**20, 1)
        configured = edge_stack.mem_limit_bytes(compose[service]["mem_limit"])
        assert abs(limit - configured) < 2**20, f"{service}: Docker's limit {limit} is not the mem_limit {configured}"
        assert used < configured, f"{service} uses {used / 2**20:.0f} MiB of its {configured / 2**20:.0f} MiB"
    assert set(usage) == set(compose)
    timings.record("memory_mib", usage)


# The gateway "local"'s facts stream as Redis holds it (run inside the redis container).
STREAM_PROBE = """
import json, redis
r = redis.Redis()
key = 'lifecycle:gw:local:facts'
group = next(g for g in r.xinfo_groups(key) if g['name'] in (b'ingest', 'ingest'))
last = group['last-delivered-id'].decode()
print(json.dumps({'ids': [e[0].decode() for e in r.xrange(key)], 'last_delivered': last,
                  'pending': group['pending'], 'undelivered': len(r.xrange(key, '(' + last, '+'))}))
"""


def facts_stream(stack) -> dict:
    probe = ["docker", "exec", stack.container("redis"), "python", "-c", STREAM_PROBE]
    return json.loads(engine.run(probe, timeout=60).stdout)


def test_facts_survive_a_redis_restart(stack, logged_in, token):
    """Facts not yet stored wait in the gateway's stream (ingest stopped); Redis restarts
    (append-only file in its volume): the entries and the consumer group's position are still
    there, and ingest, started again, stores every one of them (none lost)."""
    wait_nodes_alive(logged_in)
    key = f"{DEMO_ROBOT}.lidar_driver"
    bring_to(logged_in, token, key, "active")
    engine.run(["docker", "stop", "--time", "10", stack.container("ingest")], timeout=90)
    try:
        transition(logged_in, token, key, "deactivate")
        transition(logged_in, token, key, "activate")
        before = engine.wait_for(lambda: (f := facts_stream(stack))["undelivered"] >= 2 and f, 30,
                                 "the transitions' facts to wait in the stream")
        engine.run(["docker", "restart", "--time", "10", stack.container("redis")], timeout=120)
        after = engine.wait_for(lambda: facts_stream(stack), 60, "Redis to answer again", interval=1)
        assert set(before["ids"]) <= set(after["ids"]), "facts were lost in the Redis restart"
        assert after["last_delivered"] == before["last_delivered"], "the consumer group's position was lost"
        assert after["undelivered"] >= before["undelivered"]
    finally:
        engine.run(["docker", "start", stack.container("ingest")], timeout=90)

    def stored():
        stream = facts_stream(stack)
        response = logged_in.get(f"{PREFIX}/api/v1/gateways", headers={"Accept": "application/json"})
        local = {g["name"]: g for g in response.json()["gateways"]}["local"]
        done = stream["undelivered"] == 0 and stream["pending"] == 0 and local["backlog"] == 0 and local["online"]
        return local if done else None

    local = engine.wait_for(stored, 90, "ingest to store the waiting facts", interval=1)
    assert local["facts_lost"] == 0 and local["facts_rejected"] == 0, local
    engine.wait_for(lambda: stack.health("ingest") == "healthy", 90, "ingest healthy again")
    assert node_list(logged_in)[key]["state"]["label"] == "active"


def test_restart_keeps_audit_records_and_sessions(stack, logged_in, token):
    """Restart the gateway, then recreate web, ingest and gateway: the audit records (and the
    login session: the database and the generated secret key) live in the volume and survive."""
    wait_nodes_alive(logged_in)
    key = f"{DEMO_ROBOT}.planner"
    bring_to(logged_in, token, key, "inactive")

    def record_ids():
        response = logged_in.api("GET", f"{PREFIX}/api/v1/transitions?limit=1000", token)
        assert response.status == 200, response
        return {r["id"] for r in response.json()["transitions"]}

    before = record_ids()
    assert before
    engine.run(["docker", "restart", "--time", "10", stack.container("gateway")], timeout=120)
    transition(logged_in, token, key, "activate", timeout=90)  # the restarted gateway works again
    after_restart = record_ids()
    assert before < after_restart, "records were lost when the gateway restarted"

    stack.compose("up", "-d", "--no-deps", "--force-recreate", "web", "ingest", "gateway", timeout=300)
    for service in ("web", "ingest", "gateway"):
        engine.wait_for(lambda s=service: stack.health(s) == "healthy", 120, f"the recreated {service} container")
    assert record_ids() >= after_restart, "records were lost when the containers were recreated"
    response = logged_in.get(f"{PREFIX}/api/v1/nodes", headers={"Accept": "application/json"})
    assert response.status == 200, f"the login session did not survive: {response}"
    transition(logged_in, token, key, "deactivate", timeout=90)
