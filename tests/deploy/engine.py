"""A real Docker engine, the images and the Industrial Edge stack for the deploy tests.

Everything here is bounded in time and stopped by its own id: the Docker daemon (only when
these tests started it), the compose project, the external network, nginx.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[2]
DOCKER_DIR = ROOT / "docker"
EDGE_DIR = DOCKER_DIR / "edge"
ARTIFACTS = ROOT / "tests" / "artifacts" / "deploy"
VERSION = (DOCKER_DIR / "VERSION").read_text().strip()
IMAGE = f"lifecycle-manager:{VERSION}"
BASE_IMAGE = os.environ.get("BASE_IMAGE", "local/debian:bookworm")
DEMO_ROBOT, DEMO_DOMAIN = "agv-1", 21  # the robot container of docker/edge/docker-compose.demo.yml

# Debian packages the deploy tests need, by the program that shows they are there.
TOOLS = {
    "dockerd": "docker.io",
    "docker-compose": "docker-compose",
    "debootstrap": "debootstrap",
    "nginx": "nginx",
    "openssl": "openssl",
}


class DeployError(AssertionError):
    """Something the deploy tests need is not possible here; the message says what and why."""


def run(argv: list[str], timeout: float, check: bool = True, **kwargs) -> subprocess.CompletedProcess:
    """Run a command with a bound on its time; on failure the error shows its output."""
    try:
        result = subprocess.run(argv, capture_output=True, text=True, timeout=timeout, **kwargs)
    except subprocess.TimeoutExpired as exc:
        raise DeployError(
            f"{' '.join(argv)} did not finish within {timeout:g} s\n{_tail(exc.stdout)}\n{_tail(exc.stderr)}"
        ) from None
    if check and result.returncode != 0:
        raise DeployError(
            f"{' '.join(argv)} exited with {result.returncode}\n{_tail(result.stdout)}\n{_tail(result.stderr)}"
        )
    return result


def _tail(text, lines: int = 40) -> str:
    if not text:
        return ""
    if isinstance(text, bytes):
        text = text.decode(errors="replace")
    return "\n".join(text.splitlines()[-lines:])


def wait_for(condition: Callable[[], object], timeout: float, what: str, interval: float = 0.5):
    deadline = time.monotonic() + timeout
    last_error: Exception | None = None
    while True:
        try:
            result = condition()
            if result:
                return result
        except Exception as exc:  # noqa: BLE001 - reported if the wait runs out
            last_error = exc
        if time.monotonic() > deadline:
            detail = f" (last error: {last_error})" if last_error else ""
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}{detail}")
        time.sleep(interval)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class Timings:
    """Durations and figures of this run, shown at the end and kept in tests/artifacts/deploy."""

    def __init__(self) -> None:
        self.values: dict[str, object] = {}

    def record(self, name: str, value) -> None:
        self.values[name] = value

    def timed(self, name: str):
        timings = self

        class _Timer:
            def __enter__(self):
                self.start = time.monotonic()

            def __exit__(self, *exc):
                timings.record(name, round(time.monotonic() - self.start, 1))

        return _Timer()

    def save(self) -> None:
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        (ARTIFACTS / "figures.json").write_text(json.dumps(self.values, indent=2) + "\n")


# ---------------------------------------------------------------------------------------
# Tools and the Docker daemon


def ensure_tools() -> list[str]:
    """Install the Debian packages that are missing (as root); returns what was installed."""
    missing = sorted({pkg for tool, pkg in TOOLS.items() if not shutil.which(tool)})
    if not missing:
        return []
    if os.geteuid() != 0:
        raise DeployError(
            f"The deploy tests need {', '.join(missing)} (Debian packages) and are not root to install "
            f"them: sudo apt-get install -y {' '.join(missing)}"
        )
    # No service starts from package scripts here (nginx on :80, dockerd): we start what we need.
    policy = Path("/usr/sbin/policy-rc.d")
    made_policy = not policy.exists()
    if made_policy:
        policy.write_text("#!/bin/sh\nexit 101\n")
        policy.chmod(0o755)
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    try:
        run(["apt-get", "update", "-qq"], timeout=300, env=env)
        run(["apt-get", "install", "-y", "-qq", "--no-install-recommends", *missing], timeout=900, env=env)
    finally:
        if made_policy:
            policy.unlink()
    return missing


def docker_answers(timeout: float = 20) -> bool:
    try:
        return run(["docker", "info", "--format", "{{.ServerVersion}}"], timeout=timeout, check=False).returncode == 0
    except DeployError:
        return False


HOST_SYSCTLS = (
    "/proc/sys/net/ipv4/ip_forward",
    "/proc/sys/net/bridge/bridge-nf-call-iptables",
    "/proc/sys/net/bridge/bridge-nf-call-ip6tables",
)


@dataclass
class HostNetworkState:
    """What dockerd changes on the host and leaves behind when it stops: its iptables chains
    and FORWARD policy DROP, ip_forward, bridge netfilter (which would send other tests'
    bridged traffic through that DROP policy), docker0 and br-* interfaces."""

    tables: dict[str, str] = field(default_factory=dict)
    sysctls: dict[str, str | None] = field(default_factory=dict)
    interfaces: set[str] = field(default_factory=set)

    @classmethod
    def capture(cls) -> "HostNetworkState":
        state = cls()
        for tool in ("iptables", "ip6tables"):
            if shutil.which(f"{tool}-save"):
                result = run([f"{tool}-save"], timeout=30, check=False)
                if result.returncode == 0:
                    state.tables[tool] = result.stdout
        for path in HOST_SYSCTLS:
            state.sysctls[path] = Path(path).read_text().strip() if Path(path).exists() else None
        state.interfaces = set(os.listdir("/sys/class/net"))
        return state

    EMPTY_TABLES = {
        "filter": ("INPUT", "FORWARD", "OUTPUT"),
        "nat": ("PREROUTING", "INPUT", "OUTPUT", "POSTROUTING"),
    }

    def restore(self) -> None:
        for tool, saved in self.tables.items():
            # A table that did not exist before is restored as empty (iptables-restore only
            # replaces the tables named in its input).
            for table, chains in self.EMPTY_TABLES.items():
                if f"*{table}" not in saved:
                    saved += f"*{table}\n" + "".join(f":{c} ACCEPT [0:0]\n" for c in chains) + "COMMIT\n"
            run([f"{tool}-restore"], timeout=30, check=False, input=saved)
        for path, value in self.sysctls.items():
            if Path(path).exists():
                # Bridge netfilter was not loaded before: switch it off again.
                Path(path).write_text((value if value is not None else "0") + "\n")
        for name in set(os.listdir("/sys/class/net")) - self.interfaces:
            if name == "docker0" or name.startswith(("br-", "veth")):
                run(["ip", "link", "delete", name], timeout=30, check=False)


@dataclass
class Daemon:
    """The Docker daemon; ``process`` is set only when these tests started it."""

    process: subprocess.Popen | None = None
    log_path: Path | None = None
    host_state: HostNetworkState | None = None

    @classmethod
    def ensure(cls, workdir: Path) -> "Daemon":
        if docker_answers():
            return cls()
        if os.geteuid() != 0:
            raise DeployError("No Docker daemon answers and these tests are not root to start one (dockerd).")
        workdir.mkdir(parents=True, exist_ok=True)
        log_path = workdir / "dockerd.log"
        host_state = HostNetworkState.capture()
        with open(log_path, "ab") as log:
            process = subprocess.Popen(
                ["dockerd", "--host", "unix:///var/run/docker.sock"],
                stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
            )
        daemon = cls(process, log_path, host_state)
        deadline = time.monotonic() + 60
        while not docker_answers(timeout=5):
            if process.poll() is not None or time.monotonic() > deadline:
                daemon.stop()
                raise DeployError(
                    "Docker cannot run on this machine: dockerd "
                    + ("exited" if process.poll() is not None else "did not answer within 60 s")
                    + f". Its log ({log_path}):\n{_tail(log_path.read_text(errors='replace'))}"
                )
            time.sleep(0.5)
        return daemon

    @property
    def started_here(self) -> bool:
        return self.process is not None

    def stop(self, timeout: float = 30) -> None:
        """Stop the daemon these tests started and put the host's network settings back."""
        if self.process is None:
            return
        if self.process.poll() is None:
            os.kill(self.process.pid, signal.SIGTERM)  # dockerd stops the containerd it started
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.process.pid, signal.SIGKILL)
                self.process.wait(10)
        if self.host_state is not None:
            self.host_state.restore()


# ---------------------------------------------------------------------------------------
# Images


def build_images(timings: Timings) -> str:
    """docker/build-images.sh: base image (debootstrap when absent), wheelhouse, debs, image."""
    had_base = run(["docker", "image", "inspect", BASE_IMAGE], timeout=30, check=False).returncode == 0
    timings.record("base_image_cached", had_base)
    with timings.timed("build_images_s"):
        result = run([str(DOCKER_DIR / "build-images.sh")], timeout=1800, env={**os.environ, "BASE_IMAGE": BASE_IMAGE})
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    (ARTIFACTS / "build-images.log").write_text(result.stderr + result.stdout)
    image = result.stdout.strip().splitlines()[-1]
    size = int(run(["docker", "image", "inspect", "-f", "{{.Size}}", image], timeout=30).stdout.strip())
    timings.record("image", image)
    timings.record("image_size_mb", round(size / 1e6))
    return image


# ---------------------------------------------------------------------------------------
# The Industrial Edge stack behind an nginx that behaves like the device's


def stats_bytes(text: str) -> float:
    """A size as `docker stats` prints it: 84.17MiB, 1.2GiB, 512KiB, 900B (also kB/MB/GB)."""
    units = {"b": 1, "kib": 1024, "mib": 1024**2, "gib": 1024**3, "kb": 1000, "mb": 1000**2, "gb": 1000**3}
    match = re.fullmatch(r"\s*([\d.]+)\s*([A-Za-z]+)\s*", text)
    if not match or match.group(2).lower() not in units:
        raise ValueError(f"not a docker stats size: {text!r}")
    return float(match.group(1)) * units[match.group(2).lower()]


def mem_limit_bytes(text) -> int:
    """A compose mem_limit (160mb, 1g, 268435456): Docker reads k/m/g, with or without b, as binary."""
    match = re.fullmatch(r"\s*(\d+)\s*([bkmg]?)b?\s*", str(text).lower())
    if not match:
        raise ValueError(f"not a mem_limit: {text!r}")
    return int(match.group(1)) * {"": 1, "b": 1, "k": 1024, "m": 1024**2, "g": 1024**3}[match.group(2)]


@dataclass
class Stack:
    project: str
    workdir: Path
    files: list[str]
    web_port: int
    proxy_port: int = 0
    admin_password: str = ""
    nginx: subprocess.Popen | None = None
    created_network: bool = False
    extra: dict = field(default_factory=dict)

    def compose(self, *args: str, timeout: float = 180, check: bool = True) -> subprocess.CompletedProcess:
        argv = ["docker-compose", "-p", self.project]
        for name in self.files:
            argv += ["-f", name]
        return run(argv + list(args), timeout=timeout, check=check, cwd=self.workdir)

    def container(self, service: str) -> str:
        cid = self.compose("ps", "-q", service, timeout=60).stdout.strip()
        if not cid:
            raise AssertionError(f"no container for service {service}")
        return cid

    def health(self, service: str) -> str:
        return run(
            ["docker", "inspect", "-f", "{{if .State.Health}}{{.State.Health.Status}}{{else}}none{{end}}",
             self.container(service)], timeout=30,
        ).stdout.strip()

    def manage(self, *args: str) -> str:
        return run(["docker", "exec", self.container("web"), "python", "manage.py", *args], timeout=120).stdout.strip()

    @property
    def base_url(self) -> str:
        return f"https://127.0.0.1:{self.proxy_port}"

    def save_logs(self) -> None:
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        result = self.compose("logs", "--no-color", "--tail", "400", timeout=120, check=False)
        (ARTIFACTS / "compose.log").write_text(result.stdout + result.stderr)

    def down(self) -> None:
        """compose down (containers, networks, volume); whatever it leaves is removed by label."""
        try:
            result = self.compose("down", "-v", "--remove-orphans", "--timeout", "10", timeout=180, check=False)
            ARTIFACTS.mkdir(parents=True, exist_ok=True)
            (ARTIFACTS / "compose-down.log").write_text(f"exit {result.returncode}\n{result.stdout}{result.stderr}")
            self.down_by_label()
        finally:
            if self.created_network:
                run(["docker", "network", "rm", "proxy-redirect"], timeout=60, check=False)

    def down_by_label(self) -> None:
        label = f"label=com.docker.compose.project={self.project}"
        left = run(["docker", "ps", "-aq", "--filter", label], timeout=60, check=False).stdout.split()
        if left:
            run(["docker", "rm", "-f", "-v", *left], timeout=120, check=False)
        for kind in ("network", "volume"):
            names = run(["docker", kind, "ls", "-q", "--filter", label], timeout=60, check=False).stdout.split()
            if names:
                run(["docker", kind, "rm", *names], timeout=120, check=False)

    def leftovers(self) -> list[str]:
        label = f"label=com.docker.compose.project={self.project}"
        found = []
        for kind in ("container", "network", "volume"):
            argv = ["docker", kind, "ls", "-q", "--filter", label] + (["-a"] if kind == "container" else [])
            found += [f"{kind} {name}" for name in run(argv, timeout=60, check=False).stdout.split()]
        return found


def remove_stale_projects() -> list[str]:
    """Compose projects of earlier deploy-test runs whose pytest process is gone (a run that was
    killed before its teardown): their containers, networks and volumes are removed."""
    names = run(
        ["docker", "ps", "-a", "--format", '{{.Label "com.docker.compose.project"}}'], timeout=60, check=False
    ).stdout.split()
    stale = []
    for project in sorted(set(names)):
        match = re.fullmatch(r"lcdeploy(\d+)", project)
        if match and not Path(f"/proc/{match.group(1)}").exists():
            Stack(project=project, workdir=ROOT, files=[], web_port=0).down_by_label()
            stale.append(project)
    return stale


def nginx_location_headers(nginx_json: dict, service: str = "web") -> tuple[str, list[str], str]:
    """(name, header directives, rewrite target) of the reverse-proxy entry, as the device uses them."""
    entry = nginx_json[service][0]
    headers = json.loads(entry["headers"]) if entry.get("headers") else {}
    directives = [f'{key} "{value}";' for key, value in headers.items()]
    return entry["name"], directives, entry.get("rewriteTarget", "/")


def start_nginx(workdir: Path, proxy_port: int, web_port: int) -> subprocess.Popen:
    """Debian's nginx on loopback with TLS, set up like the device's: /<name>/ is stripped and
    proxied to the app's web service, with the headers from docker/edge/nginx.json."""
    name, header_lines, rewrite_target = nginx_location_headers(json.loads((EDGE_DIR / "nginx.json").read_text()))
    workdir.mkdir(parents=True, exist_ok=True)
    for sub in ("body", "proxy", "fastcgi", "uwsgi", "scgi"):
        (workdir / sub).mkdir(exist_ok=True)
        (workdir / sub).chmod(0o777)
    run(
        ["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
         "-keyout", str(workdir / "key.pem"), "-out", str(workdir / "cert.pem"), "-days", "2",
         "-subj", "/CN=127.0.0.1"],
        timeout=60,
    )
    headers = "\n            ".join(header_lines)
    config = f"""
worker_processes 1;
pid {workdir}/nginx.pid;
error_log {workdir}/error.log info;
events {{ worker_connections 256; }}
http {{
    access_log {workdir}/access.log;
    client_body_temp_path {workdir}/body;
    proxy_temp_path {workdir}/proxy;
    fastcgi_temp_path {workdir}/fastcgi;
    uwsgi_temp_path {workdir}/uwsgi;
    scgi_temp_path {workdir}/scgi;
    server {{
        listen 127.0.0.1:{proxy_port} ssl;
        ssl_certificate {workdir}/cert.pem;
        ssl_certificate_key {workdir}/key.pem;
        location = /{name} {{ return 301 https://$http_host/{name}/; }}
        location ~* ^/{name}/ {{
            rewrite /{name}/(.*) {rewrite_target}$1 break;
            proxy_pass http://127.0.0.1:{web_port};
            proxy_http_version 1.1;
            proxy_set_header Host $http_host;
            proxy_set_header X-Real-IP $remote_addr;
            proxy_set_header X-Forwarded-For $proxy_add_x_forwarded_for;
            {headers}
            proxy_read_timeout 300s;
        }}
    }}
}}
"""
    conf = workdir / "nginx.conf"
    conf.write_text(config)
    run(["nginx", "-t", "-p", str(workdir), "-c", str(conf)], timeout=30)
    with open(workdir / "nginx.out", "ab") as out:
        process = subprocess.Popen(
            ["nginx", "-p", str(workdir), "-c", str(conf), "-g", "daemon off;"],
            stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
        )

    def listening() -> bool:
        if process.poll() is not None:
            raise DeployError(f"nginx exited:\n{(workdir / 'error.log').read_text(errors='replace')}")
        with socket.socket() as probe:
            return probe.connect_ex(("127.0.0.1", proxy_port)) == 0

    wait_for(listening, 15, "nginx to listen")
    return process


def stop_process(process: subprocess.Popen | None, timeout: float = 10) -> None:
    if process is None or process.poll() is not None:
        return
    os.killpg(process.pid, signal.SIGTERM)
    try:
        process.wait(timeout)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait(5)


def yaml_services(path: Path) -> dict:
    import yaml

    return yaml.safe_load(path.read_text())["services"]
