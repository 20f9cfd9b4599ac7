"""The benchmark stack's processes and their shared environment: a subprocess in a process
group of its own, polling with a bound, ``manage.py`` calls, and the stack's database URL."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, TypeVar

ROOT = Path(__file__).resolve().parents[2]
PYTHON = sys.executable
CHANNEL_PREFIX = "lifecycle-bench"
DATABASE_URL_FILE = "database-url"

T = TypeVar("T")


class BenchError(RuntimeError):
    """A part of the stack did not come up or misbehaved; the message says which."""


def wait_for(condition: Callable[[], T], timeout: float, what: str, interval: float = 0.1) -> T:
    """Poll ``condition`` until it returns something truthy; BenchError after ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        result = condition()
        if result:
            return result
        if time.monotonic() > deadline:
            raise BenchError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(interval)


class Child:
    """A subprocess in its own process group, its output in a log file."""

    def __init__(self, name: str, argv: list[str], env: dict[str, str], log_dir: Path, stdin: int | None = None,
                 stdout: int | None = None) -> None:
        self.name = name
        self.log_path = log_dir / f"{name}.log"
        with open(self.log_path, "ab") as log:
            self.popen = subprocess.Popen(
                argv, cwd=ROOT, env=env, stdin=stdin if stdin is not None else subprocess.DEVNULL,
                stdout=stdout if stdout is not None else log, stderr=log, start_new_session=True,
            )

    @property
    def pid(self) -> int:
        return self.popen.pid

    def output(self) -> str:
        return self.log_path.read_text(errors="replace")

    def alive(self) -> bool:
        return self.popen.poll() is None

    def stop(self, timeout: float = 15.0) -> None:
        if self.alive():
            try:
                os.killpg(self.popen.pid, signal.SIGTERM)
                self.popen.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.popen.pid, signal.SIGKILL)
                self.popen.wait(5)
            except ProcessLookupError:
                pass


def database_url(data_dir: Path) -> str:
    """The database of the stack in ``data_dir``: its SQLite file, or the PostgreSQL database
    that ``Template.copy_to`` made for it (its URL in a file there, readable by root only)."""
    url_file = data_dir / DATABASE_URL_FILE
    if url_file.exists():
        return url_file.read_text().strip()
    return f"sqlite:///{data_dir / 'db.sqlite3'}"


def environment(data_dir: Path, redis_port: int, **extra: str) -> dict[str, str]:
    """What every process of one stack shares: settings, data dir, Redis, DDS on loopback."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("LIFECYCLE_", "DJANGO_", "ROS_")) and k != "DATABASE_URL"}
    env.update(
        DJANGO_SETTINGS_MODULE="lifecycle_site.settings",
        LIFECYCLE_DATA_DIR=str(data_dir),
        DATABASE_URL=database_url(data_dir),
        REDIS_URL=f"redis://127.0.0.1:{redis_port}/0",
        LIFECYCLE_CHANNEL_PREFIX=CHANNEL_PREFIX,
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        ROS_DOMAIN_ID="129",  # anything that forgets its domain stays in ours
        PYTHONUNBUFFERED="1",
    )
    env.update(extra)
    return env


def run_manage(env: dict[str, str], *args: str, timeout: float = 120.0) -> str:
    done = subprocess.run([PYTHON, "manage.py", *args], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=timeout)
    if done.returncode != 0:
        raise BenchError(f"manage.py {args[0]} failed:\n{done.stdout}\n{done.stderr}")
    return done.stdout


def read_env_file(path: Path) -> dict[str, str]:
    """KEY=VALUE lines, as ``manage.py add_gateway --env-file`` writes them."""
    pairs = (line.partition("=") for line in path.read_text().splitlines() if "=" in line)
    return {key.strip(): value.strip() for key, _, value in pairs}
