"""A real Docker engine, the images and the Industrial Edge stack for the deploy tests.

Everything here is bounded in time and stopped by its own id: the Docker daemon (only when
these tests started it), the compose project, the external network, nginx.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from tests.stack import free_port  # noqa: F401 (free_port used by conftest)
from tests.stack import wait_for as stack_wait_for

ROOT = Path(__file__).resolve().parents[2]
DOCKER_DIR = ROOT / "docker"
EDGE_DIR = DOCKER_DIR / "edge"
ARTIFACTS = ROOT / "tests" / "artifacts" / "deploy"
VERSION = (DOCKER_DIR / "VERSION").read_text().strip()
IMAGE = f"lifecycle-manager:{VERSION}"
BASE_IMAGE = os.environ.get("BASE_IMAGE", "local/debian:bookworm")
DEMO_ROBOT, DEMO_DOMAIN = "agv-1", 21  # the robot container of docker/edge/docker-compose.demo.yml
# A robot process on the plant LAN stand-in of the edge app's layer-2 network (tests/deploy/layer2.py).
PLANT_ROBOT, PLANT_DOMAIN = "plant-agv", 23

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
    """Containers and daemons fail in passing while they start: errors count as "not yet"."""
    return stack_wait_for(condition, timeout, what, interval=interval, tolerate=(Exception,))


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
