"""Who holds a gateway's lease, and whether that holder is provably dead.

A lease runs out on its own (its time-to-live) when its holder stops renewing it. A holder
on this host, in this boot and this PID namespace, can be checked at once: if no process
with its pid and start time exists, it has ended, and a respawned gateway need not wait out
the time-to-live (after ``kill -9`` under a supervisor, say). Elsewhere nothing can be proved
from here, and the time-to-live is the answer.
"""
from __future__ import annotations

import os
import socket
from pathlib import Path


def _read(path: str) -> str:
    try:
        return Path(path).read_text().strip()
    except OSError:
        return ""


def _start_ticks(pid: int) -> str:
    """The process's start time (clock ticks after boot), or "" if there is no such process
    or it has ended and waits to be reaped (a zombie holds no lease)."""
    stat = _read(f"/proc/{pid}/stat")
    # Fields after the command name, which is in parentheses and may hold spaces: state, ...
    fields = stat.rpartition(")")[2].split()
    if len(fields) <= 19 or fields[0] in ("Z", "X"):
        return ""
    return fields[19]


def _pid_namespace() -> str:
    try:
        return os.readlink("/proc/self/ns/pid")
    except OSError:
        return ""


def identity(instance: str) -> dict:
    """What the lease says about its holder."""
    pid = os.getpid()
    return {"instance": instance, "host": socket.gethostname(), "boot": _read("/proc/sys/kernel/random/boot_id"),
            "pidns": _pid_namespace(), "pid": pid, "start": _start_ticks(pid)}


def provably_dead(holder: dict) -> bool:
    """True only if ``holder`` ran on this host, in this boot and PID namespace, and its
    process is gone (no such pid, or another process under that pid)."""
    mine = identity("")
    same_place = all(holder.get(k) and holder.get(k) == mine[k] for k in ("host", "boot", "pidns"))
    if not same_place or not isinstance(holder.get("pid"), int) or not holder.get("start"):
        return False
    return _start_ticks(holder["pid"]) != holder["start"]
