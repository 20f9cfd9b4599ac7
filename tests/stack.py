"""Real parts for integration tests: Redis, the gateway process, demo robot processes."""
from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from copy import deepcopy
from pathlib import Path
from typing import Any, Callable
from urllib.parse import urlparse

from django.conf import settings

from ros_gateway.shared.child_process import die_with_parent

ROOT = Path(__file__).resolve().parent.parent


def environment(**extra: str) -> dict[str, str]:
    """What a subprocess needs to join this test run (same DB, Redis, ROS discovery range)."""
    env = dict(os.environ)
    env.pop("DJANGO_ALLOW_ASYNC_UNSAFE", None)  # set for Playwright in this process only
    env.update(
        DJANGO_SETTINGS_MODULE="lifecycle_site.settings",
        DATABASE_URL=_database_url(),
        PYTHONUNBUFFERED="1",
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
    )
    env.update(extra)
    return env


def _database_url() -> str:
    """The test database as a URL for child processes (tests/settings.py chose it)."""
    if settings.DATABASES["default"]["ENGINE"] == "django.db.backends.sqlite3":
        return f"sqlite:///{settings.DATABASES['default']['NAME']}"
    return os.environ["DATABASE_URL"]  # PostgreSQL: the test database is the one the URL names


def domain(offset: int) -> int:
    """A ROS domain of this test run's own (the base is drawn per run in tests/settings.py)."""
    return int(os.environ["LIFECYCLE_TEST_DOMAIN_BASE"]) + offset


def wait_for(
    condition: Callable[[], object],
    timeout: float,
    what: str,
    interval: float = 0.1,
    tolerate: tuple[type[Exception], ...] = (),
):
    """Poll ``condition`` until it returns something truthy; fail with ``what`` after ``timeout``.

    Exceptions of the ``tolerate`` types count as "not yet" (the last one is reported).
    """
    deadline = time.monotonic() + timeout
    last_error: Exception | None = None
    while True:
        try:
            result = condition()
            if result:
                return result
        except tolerate as exc:
            last_error = exc
        if time.monotonic() > deadline:
            detail = f" (last error: {last_error})" if last_error else ""
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}{detail}")
        time.sleep(interval)


def free_port() -> int:
    """A TCP port nobody listens on right now, on loopback."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class Process:
    """A child process whose output goes to a log file shown when a test fails. Started from
    the main thread, it also ends when the test run is killed (no fixture clean-up then)."""

    def __init__(self, name: str, argv: list[str], env: dict[str, str], log_dir: Path) -> None:
        self.name = name
        self.log_path = log_dir / f"{name}.log"
        log_dir.mkdir(parents=True, exist_ok=True)
        with open(self.log_path, "ab") as log:
            self.popen = subprocess.Popen(
                argv, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
                # SIGKILL when the test run dies: it also ends a process a test stopped (frozen()).
                preexec_fn=die_with_parent(signal.SIGKILL) if threading.current_thread() is threading.main_thread()
                else None,
            )

    def output(self) -> str:
        return self.log_path.read_text(errors="replace")

    def alive(self) -> bool:
        return self.popen.poll() is None

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 10.0) -> int:
        if self.alive():
            os.killpg(self.popen.pid, sig)
            try:
                self.popen.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.popen.pid, signal.SIGKILL)
                self.popen.wait(5)
        return self.popen.returncode

    def kill(self) -> None:
        self.stop(signal.SIGKILL)

    @property
    def pid(self) -> int:
        return self.popen.pid


@contextmanager
def frozen(pid: int):
    """The process stopped (SIGSTOP) for the block: it is continued afterwards, whatever happens."""
    os.kill(pid, signal.SIGSTOP)
    try:
        yield
    finally:
        try:
            os.kill(pid, signal.SIGCONT)
        except ProcessLookupError:
            pass


class Timed:
    """A call run at once in a thread of its own, timed (a request made while the test does
    something else: freezes a process, kills one). ``result()`` waits for it, bounded."""

    def __init__(self, call: Callable[[], Any]) -> None:
        self.began = time.monotonic()
        self.seconds: float | None = None
        self._box: dict[str, Any] = {}
        self._thread = threading.Thread(target=self._run, args=(call,), daemon=True)
        self._thread.start()

    def _run(self, call: Callable[[], Any]) -> None:
        from django.db import connections

        try:
            self._box["value"] = call()
        except BaseException as exc:  # noqa: BLE001 - handed to result()
            self._box["error"] = exc
        finally:
            self.seconds = time.monotonic() - self.began
            connections.close_all()  # this thread's own database connections

    def done(self) -> bool:
        return not self._thread.is_alive()

    def result(self, timeout: float) -> Any:
        self._thread.join(timeout)
        assert not self._thread.is_alive(), f"the call did not return within {timeout:g} s"
        if "error" in self._box:
            raise self._box["error"]
        return self._box["value"]


def log_dir() -> Path:
    return Path(settings.DATA_DIR) / "logs"


def start_redis():
    from lifecycle_site import local_redis

    port = urlparse(settings.REDIS_URL).port
    return local_redis.start(port, Path(settings.DATA_DIR) / "redis")


def redis_client():
    """The test run's Redis, as the site's default user sees it."""
    import redis

    return redis.Redis.from_url(settings.REDIS_URL)


def write_beat(gateway: str, *, at: float | None = None, stopped: bool = False, **fields) -> dict:
    """Play a gateway's part: write its heartbeat as the wire contract says (and make the site
    read it afresh)."""
    import socket as _socket

    from lifecycle_site.gateway_link import gateways
    from ros_gateway.shared import protocol

    beat = {
        "name": gateway, "instance": "test-instance", "version": "test", "host": _socket.gethostname(),
        "pid": os.getpid(), "started": "2026-01-01T00:00:00+00:00", "at": time.time() if at is None else at,
        "domains": [], "dds": {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}, "robots": 0, "nodes": 0,
        "outbox": {"facts": 0, "log_batches": 0, "facts_dropped": 0, "logs_dropped": 0}, "stopped": stopped,
        **fields,
    }
    redis_client().set(protocol.beat_key(gateways.channel_prefix(), gateway), protocol.encode(beat))
    gateways.forget()
    return beat


def facts_read(gateway: str) -> bool:
    """Whether the site's ingest process has read and stored every fact the gateway has sent."""
    from lifecycle_site.gateway_link import gateways
    from ros_gateway.shared import protocol

    client = redis_client()
    stream = protocol.facts_stream(gateways.channel_prefix(), gateway)
    if not client.exists(stream):
        return True
    last = client.xinfo_stream(stream)["last-generated-id"]
    groups = {g["name"]: g for g in client.xinfo_groups(stream)}
    group = groups.get(protocol.INGEST_GROUP.encode()) or groups.get(protocol.INGEST_GROUP)
    return group is not None and group["last-delivered-id"] == last and group["pending"] == 0


def start_ingest(name: str = "ingest", **env: str) -> Process:
    """The site's ingest process (``manage.py ingest``): stores what gateways report."""
    return Process(name, [sys.executable, "manage.py", "ingest"], environment(**env), log_dir())


# Every gateway of the test run gets a database it cannot open: a gateway needs only Redis,
# and any attempt to open the database would fail loudly.
GATEWAY_DATABASE_URL = "sqlite:////nonexistent-lifecycle-test-dir/no-database-for-gateways.sqlite3"


def start_gateway(name: str = "local", **env: str) -> Process:
    """``python -m ros_gateway --name NAME``, with no usable database."""
    return Process(
        name, [sys.executable, "-m", "ros_gateway", "--name", name],
        environment(**{"DATABASE_URL": GATEWAY_DATABASE_URL, **env}), log_dir(),
    )


def start_site(name: str = "daphne", **env: str) -> tuple[Process, str]:
    """The site served as ``make demo`` and the image serve it (``python -m lifecycle_site.serve``:
    daphne with answers at the HTTP layer's limits), on a free loopback port; and its base URL."""
    port = free_port()
    process = Process(
        name, [sys.executable, "-m", "lifecycle_site.serve", "-b", "127.0.0.1", "-p", str(port),
               "lifecycle_site.asgi:application"], environment(**env), log_dir(),
    )

    wait_for(lambda: listens(port) or not process.alive(), 30, f"{name} to listen")
    assert process.alive(), process.output()
    return process, f"http://127.0.0.1:{port}"


class Restartable:
    """A process that a test may stop and start again (the ingest process, Redis), under one
    object that the session fixture stops at the end, whichever instance is running then."""

    def __init__(self, start: Callable[[], object], stop: Callable[[object], None], what: str) -> None:
        self._start, self._stop, self.what = start, stop, what
        self.current: object | None = None

    def start(self) -> None:
        assert self.current is None, f"{self.what} is already running"
        self.current = self._start()

    def stop(self) -> None:
        if self.current is not None:
            self._stop(self.current)
            self.current = None


@contextmanager
def settings_redis(url: str):
    """The site (this test process) talks to another Redis for the block: commands, beats,
    configuration and Redis users all go there."""
    from django.test import override_settings

    layers = deepcopy(settings.CHANNEL_LAYERS)
    layers["default"]["CONFIG"]["hosts"] = [{**host, "address": url} for host in layers["default"]["CONFIG"]["hosts"]]
    with override_settings(REDIS_URL=url, CHANNEL_LAYERS=layers):
        yield


def start_robot(
    name: str,
    domain_id: int,
    nodes: str,
    *params: str,
    namespace: str = "",
    extra: tuple[str, ...] = (),
) -> Process:
    """Demo robot nodes in their own process; ``params`` are NODE.PARAM:=VALUE."""
    argv = [sys.executable, "-m", "ros_gateway.demo.robot", "--domain", str(domain_id), "--nodes", nodes]
    if namespace:
        argv += ["--namespace", namespace]
    for param in params:
        argv += ["--param", param]
    argv += list(extra)
    process = Process(name, argv, environment(), log_dir())
    wait_for(lambda: "demo robot ready" in process.output() or not process.alive(), 30, f"robot {name} to start")
    assert process.alive(), f"robot {name} died on start:\n{process.output()}"
    return process


@contextmanager
def nginx(workdir: Path, port: int, http: str):
    """A real nginx (Debian's) listening on 127.0.0.1:``port`` with the ``http`` block's upstreams,
    maps and server (its temp and log paths under ``workdir``), stopped on leaving."""
    binary = shutil.which("nginx") or "/usr/sbin/nginx"
    assert Path(binary).exists(), "nginx is not installed (Debian package nginx); .ci/system-packages installs it"
    (workdir / "logs").mkdir(parents=True, exist_ok=True)
    paths = "\n".join(f"    {kind}_temp_path {workdir}/{kind.split('_')[0]};"
                      for kind in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi"))
    (workdir / "nginx.conf").write_text(
        f"daemon off;\nworker_processes 1;\npid {workdir}/nginx.pid;\nerror_log {workdir}/logs/error.log warn;\n"
        f"events {{ worker_connections 256; }}\nhttp {{\n    access_log {workdir}/logs/access.log;\n{paths}\n"
        f"    map $http_upgrade $connection_upgrade {{ default upgrade; '' close; }}\n{http}\n}}\n"
    )
    process = subprocess.Popen([binary, "-p", str(workdir), "-c", str(workdir / "nginx.conf")],
                               stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    try:
        wait_for(lambda: listens(port) or process.poll() is not None, 15, "nginx to listen")
        assert process.poll() is None, (workdir / "logs" / "error.log").read_text()
        yield process
    finally:
        process.terminate()
        process.wait(10)


def pid_alive(pid: int) -> bool:
    """Whether the process runs (a zombie waiting to be reaped does not)."""
    try:
        os.kill(pid, 0)
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except (ProcessLookupError, FileNotFoundError):
        return False


def listens(port: int) -> bool:
    """Whether something accepts connections on 127.0.0.1:``port``."""
    with socket.socket() as probe:
        return probe.connect_ex(("127.0.0.1", port)) == 0
