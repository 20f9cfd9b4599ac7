"""The real stack of one scenario: its own Redis, a fresh database (SQLite, or with
``--database postgres`` a database of its own on a throw-away PostgreSQL cluster), and as
subprocesses the site's ingest process, one registered gateway (with its own Redis user and
no database) and daphne; robot processes on demand. Everything is stopped on exit.

DDS stays on this machine (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST) and the benchmark uses
ROS domains 120-131 only, apart from the tests (30-119, 132-221) and the demo (21, 22). Each
scenario claims its domains (tests/domains.py), so two runs on one machine cannot share one.
"""
from __future__ import annotations

import json
import socket
import sqlite3
import subprocess
from pathlib import Path

from tests import domains
from tests.benchmarks.processes import (
    CHANNEL_PREFIX,
    PYTHON,
    BenchError,
    Child,
    database_url,
    environment,
    read_env_file,
    run_manage,
    wait_for,
)
from tests.benchmarks.system import free_port
from tests.benchmarks.template import PASSWORD, USER, Template
from tests.benchmarks.web import Http

# The gateway gets a database it cannot open, as in the integration tests: it needs only Redis.
GATEWAY_DATABASE_URL = "sqlite:////nonexistent-lifecycle-bench-dir/no-database-for-gateways.sqlite3"


class Stack:
    """Redis, database, ingest, gateway and daphne of one scenario (a context manager)."""

    api: Http  # bearer token of the benchmark's operator
    web: Http  # the same operator's browser session (login form)

    def __init__(self, workdir: Path, template: Template, name: str, robots: list[tuple[str, int]],
                 **env_extra: str) -> None:
        self.name = name
        self.dir = workdir / name
        template.copy_to(self.dir)
        self.log_dir = self.dir / "logs"
        self.log_dir.mkdir()
        self.token = template.token
        self.redis_port, self.web_port = free_port(), free_port()
        self.env = environment(self.dir, self.redis_port, **env_extra)
        self.robots = robots
        self.children: list[Child] = []
        self.redis: subprocess.Popen | None = None
        self.gateway: Child | None = None
        self.ingest: Child | None = None
        self.site: Child | None = None
        self.gateway_name = f"bench-{name}"
        self.stats_path = self.dir / "gateway-stats.json"
        self.db_path = self.dir / "db.sqlite3"
        self._db = None  # sqlite3 or psycopg connection, made on first use
        self._redis = None  # the harness's own Redis client (default user), made on first use
        self.more_gateways: dict[str, Child] = {}  # add_gateway(): name -> process
        self.more_domains: list[int] = []

    # -- bring-up and teardown ------------------------------------------------------------
    def __enter__(self) -> "Stack":
        try:
            self.start()
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self) -> None:
        from lifecycle_site import local_redis

        try:
            domains.claim(sorted({domain for _, domain in self.robots}))
        except domains.DomainInUse as exc:
            raise BenchError(f"{exc}: wait for the other benchmark run to end") from None
        self.redis = local_redis.start(self.redis_port, self.dir / "redis")
        # As an operator sets up a gateway (docs/architecture.md): register it, which gives it a
        # Redis user of its own and writes its environment, then its robots.
        env_file = self.dir / "gateway.env"
        run_manage(self.env, "add_gateway", self.gateway_name, "--env-file", str(env_file))
        for robot, domain in self.robots:
            run_manage(self.env, "add_robot", robot, "--domain", str(domain), "--gateway", self.gateway_name)
        self.ingest = self.spawn("ingest", [PYTHON, "manage.py", "ingest"])
        gateway_env = dict(self.env, DATABASE_URL=GATEWAY_DATABASE_URL, **read_env_file(env_file))
        self.gateway = self.spawn(
            "gateway", [PYTHON, "-m", "tests.benchmarks.gateway_main", self.gateway_name, str(self.stats_path)],
            env=gateway_env,
        )
        self.site = self.spawn(
            "daphne", [PYTHON, "-m", "lifecycle_site.serve", "-b", "127.0.0.1", "-p", str(self.web_port),
                       "lifecycle_site.asgi:application"]
        )
        wait_for(lambda: self._answers() or not self.site.alive(), 30, "daphne to listen")
        self._require_alive(self.site)
        self.api = Http("127.0.0.1", self.web_port, token=self.token)
        wait_for(lambda: "holding the ingest lease" in self.ingest.output() or not self.ingest.alive(), 60,
                 "the ingest process to take its lease")
        self._require_alive(self.ingest)
        wait_for(lambda: self._gateway_online() or not self.gateway.alive(), 60, "the gateway heartbeat")
        self._require_alive(self.gateway)
        self.web = Http("127.0.0.1", self.web_port)
        self.web.login(USER, PASSWORD)

    def stop(self) -> None:
        if self._db is not None:
            self._db.close()
            self._db = None
        if self._redis is not None:
            self._redis.close()
            self._redis = None
        for child in reversed(self.children):
            child.stop()
        self.children.clear()
        if self.redis is not None and self.redis.poll() is None:
            self.redis.terminate()
            self.redis.wait(10)
        domains.release(sorted({domain for _, domain in self.robots}))
        domains.release(self.more_domains)

    def spawn(self, name: str, argv: list[str], env: dict[str, str] | None = None, **kwargs: int) -> Child:
        child = Child(name, argv, env or self.env, self.log_dir, **kwargs)
        self.children.append(child)
        return child

    def _answers(self) -> bool:
        with socket.socket() as probe:
            return probe.connect_ex(("127.0.0.1", self.web_port)) == 0

    def _gateway_online(self) -> bool:
        response = self.api.get("/api/v1/robots")
        return response.status == 200 and response.json()["gateway_online"]

    @staticmethod
    def _require_alive(child: Child) -> None:
        if not child.alive():
            raise BenchError(f"{child.name} exited on start:\n{child.output()[-3000:]}")

    # -- more gateways (the fleet scenario) ------------------------------------------------
    def add_gateway(self, name: str, robots: list[tuple[str, int]]) -> Child:
        """Another gateway with robots of its own, registered as the first one (one Django start
        for all its ``add_gateway``/``add_robot`` commands), its counters in gateway_stats(name)."""
        wanted = sorted({domain for _, domain in robots})
        try:
            domains.claim(wanted)
        except domains.DomainInUse as exc:
            raise BenchError(f"{exc}: wait for the other benchmark run to end") from None
        self.more_domains.extend(wanted)
        env_file = self.dir / f"gateway-{name}.env"
        commands = [f"call_command('add_gateway', {name!r}, env_file={str(env_file)!r})"] + [
            f"call_command('add_robot', {robot!r}, domain={domain}, gateway={name!r})" for robot, domain in robots]
        run_manage(self.env, "shell", "-c", "from django.core.management import call_command\n" + "\n".join(commands))
        gateway_env = dict(self.env, DATABASE_URL=GATEWAY_DATABASE_URL, **read_env_file(env_file))
        child = self.spawn(f"gateway-{name}", [PYTHON, "-m", "tests.benchmarks.gateway_main", name,
                                               str(self.dir / f"gateway-stats-{name}.json")], env=gateway_env)
        self.more_gateways[name] = child
        names = {robot for robot, _ in robots}

        def online() -> bool:
            listed = self.api.get("/api/v1/robots")
            return listed.status == 200 and all(r["gateway_online"] for r in listed.json()["robots"]
                                                if r["name"] in names)

        wait_for(lambda: online() or not child.alive(), 60, f"the heartbeat of gateway {name}")
        self._require_alive(child)
        return child

    # -- robots ---------------------------------------------------------------------------
    def start_robot(self, name: str, domain: int, generic: int, prefix: str, nodes: str = "",
                    wait: bool = True) -> Child:
        """A demo robot process with ``generic`` minimal lifecycle nodes (<prefix>_000 ...)."""
        argv = [PYTHON, "-m", "ros_gateway.demo.robot", "--domain", str(domain), "--nodes", nodes,
                "--generic", str(generic), "--generic-prefix", prefix, "--ros-args", "--disable-external-lib-logs"]
        child = self.spawn(name, argv)
        if wait:
            self.wait_robot(child)
        return child

    def wait_robot(self, child: Child, timeout: float = 90.0) -> None:
        wait_for(lambda: "demo robot ready" in child.output() or not child.alive(), timeout, f"{child.name} to start")
        self._require_alive(child)

    # -- what the stack reports -----------------------------------------------------------
    def gateway_stats(self, name: str | None = None) -> dict:
        """Counters the gateway wrapper writes every half second (see gateway_main.py); ``name``:
        one added by add_gateway()."""
        path = self.dir / f"gateway-stats-{name}.json" if name else self.stats_path
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError):
            return {}

    def ingest_stats(self) -> dict:
        """What the ingest process has stored, read where it stores it (the database; read-only
        queries, WAL lets them run beside its writes): log records ever stored (the highest id:
        pruning deletes old rows, never the newest), audit records by source, and the gateway
        row's accounts of what was lost on the way and its node count (copied from its beat)."""
        url = database_url(self.dir)
        if self._db is None and url.startswith("postgres"):
            import psycopg

            self._db = psycopg.connect(url, autocommit=True)
        elif self._db is None:
            self._db = sqlite3.connect(self.db_path, timeout=10, isolation_level=None, check_same_thread=False)
        db = self._db
        mark = "?" if isinstance(db, sqlite3.Connection) else "%s"
        stats: dict = {
            "logs_stored": db.execute("SELECT coalesce(max(id), 0) FROM fleet_logrecord").fetchone()[0],
            "audit_records": dict(
                db.execute("SELECT source, count(*) FROM audit_transitionrecord GROUP BY source").fetchall()),
        }
        columns = ("logs_lost", "logs_dropped", "facts_lost", "facts_rejected", "node_count")
        row = db.execute(f"SELECT {', '.join(columns)} FROM fleet_gateway WHERE name = {mark}",
                         (self.gateway_name,)).fetchone()
        if row is not None:
            stats.update(zip(columns, row, strict=True))
        return stats

    def stream_backlog(self, kind: str = "logs") -> int:
        """Entries of the gateway's ``kind`` stream in Redis that the ingest process has not yet
        acknowledged: not yet delivered (the group's lag) plus delivered and not acknowledged."""
        import redis

        from ros_gateway.shared import protocol

        if self._redis is None:
            self._redis = redis.Redis(host="127.0.0.1", port=self.redis_port, socket_timeout=5)
        key = protocol.gateway_key(CHANNEL_PREFIX, self.gateway_name, kind)
        for group in self._redis.xinfo_groups(key):
            if group["name"] in (protocol.INGEST_GROUP, protocol.INGEST_GROUP.encode()):
                return int(group.get("lag") or 0) + int(group.get("pending") or 0)
        return self._redis.xlen(key)

    def nodes(self, robot: str | None = None) -> list[dict]:
        path = "/api/v1/nodes" + (f"?robot={robot}" if robot else "")
        response = self.api.get(path)
        if response.status != 200:
            raise BenchError(f"GET {path} answered {response.status}: {response.body[:300]!r}")
        return response.json()["nodes"]

    def wait_nodes(self, keys: list[str], timeout: float, state: str | None = None) -> None:
        """Until every listed node is alive (and in ``state``, when given)."""
        wanted = set(keys)

        def ready() -> bool:
            listed = {n["id"]: n for n in self.nodes()}
            return all(
                k in listed and listed[k]["alive"] and (state is None or listed[k]["state"]["label"] == state)
                for k in wanted
            )

        wait_for(ready, timeout, f"{len(wanted)} nodes to be listed alive" + (f" and {state}" if state else ""), 0.25)


class BenchContext:
    """What every scenario gets: a work dir, the template database, the run's options."""

    def __init__(self, workdir: Path, template: Template, quick: bool, profile_dir: Path | None,
                 web_processes: int | None = None) -> None:
        self.workdir = workdir
        self.template = template
        self.quick = quick
        self.profile_dir = profile_dir
        self.web_processes = web_processes

    def stack(self, name: str, robots: list[tuple[str, int]], **env_extra: str) -> Stack:
        if self.web_processes is not None:
            env_extra.setdefault("LIFECYCLE_WEB_PROCESSES", str(self.web_processes))
        return Stack(self.workdir, self.template, name, robots, **env_extra)
