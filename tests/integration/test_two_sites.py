"""Two site instances (daphne) behind one nginx, sharing the test run's database and Redis, as
a bigger site runs: pages, commands and WebSocket pushes work through either instance.

nginx spreads requests over both (round robin) and says in a response header which one
answered; a request carrying ``X-Instance: a`` or ``b`` goes to that one only, so the test can
hold a socket on one instance and send a command through the other. On PostgreSQL
(``make test-postgres``) this is the deployment the issue asks for; on SQLite the two
instances share the database file."""
from __future__ import annotations

import asyncio
import http.client
import json
import re
import textwrap
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlencode

import pytest
from django.conf import settings
from websockets.asyncio.client import connect

from lifecycle_site.api.models import ApiToken
from tests import stack
from tests.benchmarks.web import CSRF_FIELD
from tests.conftest import make_user
from tests.integration.conftest import register, wait_node

ROBOT = "two-sites-agv"
PASSWORD = "a-test-password-123"  # tests.conftest.make_user's
CSRF_META = re.compile(r'X-CSRFToken&quot;: &quot;([^&]+)&quot;')


@pytest.fixture(scope="module")
def robot(gateway):
    register(ROBOT, stack.domain(27))
    process = stack.start_robot("two-sites-nodes", stack.domain(27), "lidar_driver,camera_driver")
    yield process
    process.stop()


@pytest.fixture(scope="module")
def sites(gateway):
    """Two daphne processes, each with its own port: {"a": base URL, "b": base URL}."""
    started: list[stack.Process] = []
    try:
        bases = {}
        for name in ("a", "b"):
            process, bases[name] = stack.start_site(f"two-sites-daphne-{name}")
            started.append(process)
        yield bases
    finally:
        for process in started:
            process.stop()


@pytest.fixture(scope="module")
def nginx(sites):
    """One nginx in front of both instances: its port, and each instance's upstream address."""
    port = stack.free_port()
    upstreams = {name: base.removeprefix("http://") for name, base in sites.items()}
    http = textwrap.dedent(f"""
        upstream site {{ server {upstreams['a']}; server {upstreams['b']}; }}
        upstream site_a {{ server {upstreams['a']}; }}
        upstream site_b {{ server {upstreams['b']}; }}
        map $http_x_instance $pick {{ default site; a site_a; b site_b; }}
        server {{
            listen 127.0.0.1:{port};
            location / {{
                proxy_pass http://$pick;
                proxy_http_version 1.1;
                proxy_set_header Upgrade $http_upgrade;
                proxy_set_header Connection $connection_upgrade;
                proxy_set_header Host $host:$server_port;
                proxy_read_timeout 120s;
                add_header X-Upstream $upstream_addr always;
            }}
        }}
    """)
    with stack.nginx(Path(settings.DATA_DIR) / "two-sites-nginx", port, http):
        yield port, upstreams



@dataclass
class Answer:
    status: int
    upstream: str  # the instance that answered, as nginx names it (X-Upstream)
    body: str

    def json(self):
        return json.loads(self.body)


class Web:
    """A client of the site through nginx (a new connection per request, as round robin spreads
    requests anyway): a session from the login form or a bearer token."""

    def __init__(self, port: int, token: str | None = None) -> None:
        self.port, self.token = port, token
        self.cookies: dict[str, str] = {}

    def request(self, method: str, path: str, body: str | None = None, instance: str | None = None,
                **headers: str) -> Answer:
        headers = {key.replace("_", "-"): value for key, value in headers.items()}
        if instance:
            headers["X-Instance"] = instance
        if self.token:
            headers["Authorization"] = f"Bearer {self.token}"
        if self.cookies:
            headers["Cookie"] = self.cookie_header()
        connection = http.client.HTTPConnection("127.0.0.1", self.port, timeout=60)
        try:
            connection.request(method, path, body=body, headers=headers)
            answer = connection.getresponse()
            data = answer.read().decode(errors="replace")
        finally:
            connection.close()
        for cookie in answer.headers.get_all("Set-Cookie") or []:
            name, _, value = cookie.split(";", 1)[0].partition("=")
            self.cookies[name.strip()] = value.strip()
        return Answer(answer.status, answer.getheader("X-Upstream", ""), data)

    def login(self, username: str, password: str) -> None:
        page = self.request("GET", "/login/")
        form = urlencode({"username": username, "password": password,
                          "csrfmiddlewaretoken": CSRF_FIELD.search(page.body).group(1)})
        answer = self.request("POST", "/login/", form, Content_Type="application/x-www-form-urlencoded")
        assert answer.status == 302 and "sessionid" in self.cookies, (answer.status, answer.body[:500])

    def cookie_header(self) -> str:
        return "; ".join(f"{k}={v}" for k, v in self.cookies.items())


async def push_seen(web: Web, instance: str, key: str, send, want: str, timeout: float = 20.0) -> tuple[str, str]:
    """Hold the node's socket on ``instance`` (through nginx), then call ``send()`` (a command
    through the other instance) and wait for the state panel pushed with ``want`` in it.
    Returns the upstream the socket went to and the command's upstream."""
    headers = {"Cookie": web.cookie_header(), "X-Instance": instance}
    async with connect(f"ws://127.0.0.1:{web.port}/ws/nodes/{key}/", origin=f"http://127.0.0.1:{web.port}",
                       additional_headers=headers, compression=None, proxy=None, open_timeout=10,
                       max_size=8 * 1024 * 1024) as ws:
        socket_upstream = ws.response.headers["X-Upstream"]
        await asyncio.sleep(0.5)  # subscribed to the node's group
        command_upstream = await asyncio.to_thread(send)
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while True:
            message = await asyncio.wait_for(ws.recv(), max(deadline - loop.time(), 0.1))
            if 'id="node-state"' in message and f'state-{want}"' in message:
                return socket_upstream, command_upstream


def test_pages_commands_and_pushes_work_through_either_instance(nginx, sites, robot):
    port, upstreams = nginx
    key = f"{ROBOT}.lidar_driver"
    wait_node(None, key, alive=True, state="unconfigured")
    user = make_user("tina-two-sites", "operator")
    token = ApiToken.issue(user, "two-sites")[1]
    web, api = Web(port), Web(port, token=token)
    # Logged in through nginx (the login page and the form post may land on either instance).
    web.login(user.username, PASSWORD)
    # Pages: round robin serves them from both instances, with the one session.
    served = set()
    for _ in range(6):
        answer = web.request("GET", f"/nodes/{key}/")
        assert answer.status == 200 and ROBOT in answer.body, (answer.status, answer.body[:500])
        served.add(answer.upstream)
    assert served == set(upstreams.values()), served
    for name, upstream in upstreams.items():
        answer = web.request("GET", "/", instance=name)
        assert (answer.status, answer.upstream) == (200, upstream) and key in answer.body

    # A command through instance a (the node page's button: session and CSRF token); its push
    # reaches a socket held through instance b.
    csrf = CSRF_META.search(web.request("GET", f"/nodes/{key}/", instance="a").body).group(1)

    def configure_through_a() -> str:
        answer = web.request("POST", f"/nodes/{key}/transition", "transition=configure", instance="a",
                             Content_Type="application/x-www-form-urlencoded", X_CSRFToken=csrf,
                             HX_Request="true", HX_Target="transition-result")
        assert answer.status == 200 and "state-inactive" in answer.body, answer.body[:500]
        return answer.upstream

    held, sent = asyncio.run(push_seen(web, "b", key, configure_through_a, "inactive"))
    assert (held, sent) == (upstreams["b"], upstreams["a"])

    # And the other way: an API command through instance b, pushed on a socket held through a.
    def activate_through_b() -> str:
        answer = api.request("POST", f"/api/v1/nodes/{key}/transition", '{"transition": "activate"}',
                             instance="b", Content_Type="application/json")
        assert answer.status == 200 and answer.json()["to"]["label"] == "active", answer.body[:500]
        return answer.upstream

    held, sent = asyncio.run(push_seen(web, "a", key, activate_through_b, "active"))
    assert (held, sent) == (upstreams["a"], upstreams["b"])
    # Both commands are in the one audit trail, whichever instance took them.
    records = api.request("GET", f"/api/v1/transitions?node={key}&limit=2").json()["transitions"]
    assert [r["transition"]["label"] for r in records] == ["activate", "configure"], records
