"""Processes of launch profiles that a killed gateway left running, ended by its next instance.

The supervisor's child gets SIGTERM from the kernel when the gateway dies (PR_SET_PDEATHSIG), but
only that child: a profile run through a shell or a script leaves its own children running
(orphans the next instance would start again beside). So every supervised process is started
with a mark in its environment, ``LIFECYCLE_SUPERVISED_BY=GATEWAY@SITE/ROBOT/PROFILE``, which its
children inherit; the next instance of that gateway (of that site), once it holds the gateway's lease (so its
predecessor is gone), ends every process of this host that carries its name: SIGTERM, then
SIGKILL after GRACE_S. It reads the environments it may read (its own user's, or all as root).
"""
from __future__ import annotations

import asyncio
import contextlib
import hashlib
import os
import signal
import time
from pathlib import Path
from urllib.parse import urlsplit

from ros_gateway.processes import stat_fields

MARK = "LIFECYCLE_SUPERVISED_BY"
GRACE_S, POLL_S = 3.0, 0.1


def owner(gateway: str, redis_url: str, prefix: str) -> str:
    """Who runs the processes: the gateway's name and a digest of its site (Redis server and
    channel prefix, not the password): ``make demo`` and a test run on one host may both have a
    gateway "local", and neither may end the other's processes."""
    parts = urlsplit(redis_url)
    site = f"{parts.hostname}:{parts.port}{parts.path}#{prefix}"
    return f"{gateway}@{hashlib.blake2b(site.encode(), digest_size=5).hexdigest()}"


def mark(gateway: str, robot: str, profile: str) -> str:
    return f"{gateway}/{robot}/{profile}"


def _marked(proc: Path, pid: int, prefix: bytes) -> str | None:
    """The process's mark if it begins with ``prefix`` (b"MARK=GATEWAY/"), else None."""
    try:
        environ = (proc / str(pid) / "environ").read_bytes()
    except OSError:  # gone, or not ours to read
        return None
    for entry in environ.split(b"\0"):
        if entry.startswith(prefix):
            return entry[len(MARK) + 1:].decode(errors="replace")
    return None


def find(gateway: str, proc: Path = Path("/proc")) -> dict[int, str]:
    """pid -> mark of this host's processes marked as run for ``gateway`` (not this process)."""
    prefix, own = f"{MARK}={gateway}/".encode(), os.getpid()
    try:
        pids = [int(name) for name in os.listdir(proc) if name.isdigit() and int(name) != own]
    except OSError:
        return {}
    return {pid: found for pid in pids if (found := _marked(proc, pid, prefix)) is not None}


async def end(gateway: str, proc: Path = Path("/proc")) -> dict[str, list[int]]:
    """End what a previous instance of ``gateway`` left running; mark -> the pids ended."""
    left = find(gateway, proc)
    for pid in left:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(pid, signal.SIGTERM)
    deadline = time.monotonic() + GRACE_S
    while time.monotonic() < deadline and any(_alive(proc, pid) for pid in left):
        await asyncio.sleep(POLL_S)
    for pid in left:
        if _alive(proc, pid):
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, signal.SIGKILL)
    ended: dict[str, list[int]] = {}
    for pid, found in sorted(left.items()):
        ended.setdefault(found, []).append(pid)
    return ended


def _alive(proc: Path, pid: int) -> bool:
    fields = stat_fields(proc, pid)
    return bool(fields) and fields[0] not in ("Z", "X")
