"""The site, its ingest process and a gateway with its own Redis user, all over TLS
(``rediss://``) to Debian's redis-server, with a certificate authority this test makes."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest
from django.core.management import call_command

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import Gateway, ManagedNode, Robot
from tests import stack
from tests.conftest import make_user
from tests.integration.conftest import register, wait_node


def make_certificates(folder: Path) -> tuple[Path, Path, Path]:
    """A CA, and a server certificate for 127.0.0.1 signed by it (openssl, as an operator would)."""
    ca_key, ca, key, csr, cert = (folder / n for n in ("ca.key", "ca.crt", "redis.key", "redis.csr", "redis.crt"))
    ext = folder / "san.cnf"
    ext.write_text("subjectAltName=IP:127.0.0.1,DNS:localhost\n")
    run = [
        ["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj", "/CN=test-ca",
         "-keyout", ca_key, "-out", ca],
        ["openssl", "req", "-newkey", "rsa:2048", "-nodes", "-subj", "/CN=127.0.0.1", "-keyout", key, "-out", csr],
        ["openssl", "x509", "-req", "-in", csr, "-CA", ca, "-CAkey", ca_key, "-CAcreateserial", "-days", "2",
         "-extfile", ext, "-out", cert],
    ]
    for argv in run:
        subprocess.run([str(a) for a in argv], check=True, capture_output=True)
    key.chmod(0o600)
    return ca, cert, key


@pytest.fixture(scope="module")
def tls_redis(tmp_path_factory):
    binary = shutil.which("redis-server")
    assert binary, "Debian's redis-server is needed (make test installs it)"
    folder = tmp_path_factory.mktemp("tls")
    ca, cert, key = make_certificates(folder)
    port = stack.free_port()
    process = subprocess.Popen(
        [binary, "--port", "0", "--tls-port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
         "--tls-cert-file", str(cert), "--tls-key-file", str(key), "--tls-ca-cert-file", str(ca),
         "--tls-auth-clients", "no", "--dir", str(folder)],
        stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT,
    )
    url = f"rediss://127.0.0.1:{port}/0?ssl_ca_certs={ca}"
    stack.wait_for(lambda: _ping(url), 10, "the TLS Redis")
    yield url
    process.terminate()
    process.wait(5)


def _ping(url: str) -> bool:
    import redis

    try:
        return bool(redis.Redis.from_url(url, socket_connect_timeout=1).ping())
    except redis.RedisError:
        return False


def test_a_transition_through_a_tls_only_redis(tls_redis, live_db, tmp_path):
    site_env = {"REDIS_URL": tls_redis}
    make_user("tina-tls", "operator")
    token = subprocess.run([sys.executable, "manage.py", "create_api_token", "tina-tls"], env=stack.environment(),
                           capture_output=True, text=True, check=True).stdout.strip()
    env_file = tmp_path / "cell-tls.env"
    with stack.settings_redis(tls_redis):  # the site's Redis: users and the robots' config go there
        call_command("add_gateway", "cell-tls", env_file=str(env_file))
        register("tls-agv", stack.domain(24), gateway="cell-tls")
    gateway_env = dict(line.split("=", 1) for line in env_file.read_text().splitlines() if "=" in line)
    assert gateway_env["REDIS_URL"].startswith("rediss://gw-cell-tls:")
    port = stack.free_port()
    processes = [
        stack.Process("tls-ingest", [sys.executable, "manage.py", "ingest"], stack.environment(**site_env),
                      stack.log_dir()),
        stack.start_gateway("cell-tls", **gateway_env),
        stack.Process("tls-daphne", [sys.executable, "-m", "lifecycle_site.serve", "-b", "127.0.0.1", "-p", str(port),
                                     "lifecycle_site.asgi:application"], stack.environment(**site_env),
                      stack.log_dir()),
        stack.start_robot("tls-robot", stack.domain(24), "lidar_driver"),
    ]
    try:
        wait_node(None, "tls-agv.lidar_driver", alive=True, state="unconfigured", timeout=40)
        request = urllib.request.Request(
            f"http://127.0.0.1:{port}/api/v1/nodes/tls-agv.lidar_driver/transition",
            data=json.dumps({"transition": "configure"}).encode(), method="POST",
            headers={"Authorization": f"Bearer {token}", "Content-Type": "application/json"},
        )
        stack.wait_for(lambda: _answers(port), 20, "daphne")
        with urllib.request.urlopen(request, timeout=30) as response:
            answer = json.loads(response.read())
        assert answer["to"]["label"] == "inactive", answer
        record = TransitionRecord.objects.get(id=answer["record_id"])
        assert (record.outcome, record.requested_by_name) == ("succeeded", "tina-tls")
        assert ManagedNode.objects.get(key="tls-agv.lidar_driver").state_label == "inactive"
    finally:
        for process in reversed(processes):
            process.stop()
        with stack.settings_redis(tls_redis):  # later tests' pages must not show this gateway offline
            Robot.objects.filter(name="tls-agv").delete()
            Gateway.objects.filter(name="cell-tls").delete()


def _answers(port: int) -> bool:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/login/", timeout=2):
            return True
    except OSError:
        return False
