"""Containers and systemd units that run a robot's nodes on the gateway's host: which one a
node's process is in (its cgroup), and restarting, stopping and starting it through its own
supervisor: the Docker Engine (its API on a Unix socket) or systemd (``systemctl``).

Safety: a unit is acted on only once the gateway has attributed it to one of a robot's nodes
itself (the node's DDS participant -> this host's process -> its cgroup). A request names that
attribution ("docker:drivers", "systemd:agv-drivers.service"), looked up here for that robot;
never a container id, unit or pid of its own. A unit stays attributed after its nodes have gone
(so a stopped one can be started), until the gateway restarts or LIMIT newer ones pushed it out.
"""
from __future__ import annotations

import asyncio
import contextlib
import http.client
import json
import logging
import os
import re
import shutil
import socket
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Callable
from urllib.parse import quote

from ros_gateway.shared import protocol
from ros_gateway.supervisor import SIGNAL_NAMES

log = logging.getLogger(__name__)

CONTAINER_IN_CGROUP = re.compile(r"(?:^|/)(?:docker[-/])([0-9a-f]{64})(?:\.scope)?(?=/|$)")
LIMIT = 256  # units remembered per gateway; cgroups looked up
REPLY_LIMIT = 1 << 20  # bytes of one Docker Engine answer
CALL_S, MARGIN_S, MAX_GRACE_S = 5.0, 10.0, 120.0  # one quick call; over a stop's grace; a unit's stop time at most
ASK_AGAIN_FIRST_S, ASK_AGAIN_MAX_S = 2.0, 120.0  # a container the engine could not name: asked again after


@dataclass(frozen=True)
class HostUnit:
    kind: str  # "docker" or "systemd"
    ident: str  # the container's id, or the unit's name
    name: str  # what the site calls it: "docker:<container name>", "systemd:<unit>"


class UnitError(Exception):
    """The unit's supervisor refused or did not answer; the message says so in words."""


def cgroup_path(text: str) -> str:
    """The process's cgroup: systemd's own hierarchy where there is one (v1 and hybrid hosts: the
    only one with a systemd inside a container's units), else v2's unified one; "" if neither."""
    lines = dict(line.split(":", 2)[1:] for line in text.splitlines() if line.count(":") >= 2)
    systemd = lines.get("name=systemd", "")
    return systemd if systemd not in ("", "/") else lines.get("", systemd)


def unit_in(path: str, own: str = "") -> tuple[str, str] | None:
    """("docker", container id) or ("systemd", unit) that a cgroup path belongs to, or None.
    Inside the gateway's own container (``own``: the gateway's cgroup) only systemd units count:
    they are that container's (a robot's systemd in a container), the container is not the node's."""
    container = CONTAINER_IN_CGROUP.search(path)
    if container and not (own and container.group(1) in own):
        return "docker", container.group(1)
    parts = path.split("/")
    if "system.slice" in parts:  # a system unit (a user's units are another manager's)
        unit = parts[parts.index("system.slice") + 1:][:1]
        if unit and unit[0].endswith(".service"):
            return "systemd", unit[0]
    return None


def _exit_words(code: int | None, sig: str | None) -> str:
    return f"ended by {sig}" if sig else f"exited with status {code}" if code is not None else "ended"


class _UnixHTTP(http.client.HTTPConnection):
    def __init__(self, path: str, timeout: float) -> None:
        super().__init__("localhost", timeout=timeout)
        self.socket_path = path

    def connect(self) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.settimeout(self.timeout)
        self.sock.connect(self.socket_path)


class DockerEngine:
    """The few calls of the Docker Engine API the gateway needs, over its Unix socket; each bounded."""

    def __init__(self, socket_path: str) -> None:
        self.socket_path = socket_path

    def available(self) -> bool:
        return bool(self.socket_path) and os.path.exists(self.socket_path)

    def _call(self, method: str, path: str, timeout: float) -> tuple[int, object]:
        conn = _UnixHTTP(self.socket_path, timeout)
        try:
            conn.request(method, path, headers={"Content-Length": "0"} if method == "POST" else {})
            response = conn.getresponse()
            body = response.read(REPLY_LIMIT + 1)
        finally:
            conn.close()
        if len(body) > REPLY_LIMIT:
            raise UnitError(f"the Docker Engine's answer to {path} is over {REPLY_LIMIT} bytes")
        try:
            data = json.loads(body) if body else None
        except ValueError:
            data = None
        return response.status, data

    async def call(self, method: str, path: str, timeout: float = CALL_S) -> tuple[int, object]:
        try:
            return await asyncio.wait_for(asyncio.to_thread(self._call, method, path, timeout), timeout + 1.0)
        except (OSError, http.client.HTTPException, asyncio.TimeoutError) as exc:
            why = "no answer within %g s" % timeout if isinstance(exc, (asyncio.TimeoutError, TimeoutError)) else exc
            raise UnitError(f"the Docker Engine at {self.socket_path} could not be asked ({why})") from None

    async def inspect(self, ident: str) -> dict:
        status, data = await self.call("GET", f"/containers/{quote(ident)}/json")
        if status == 404:
            raise UnitError(f"container {ident[:12]} no longer exists")
        if status != 200 or not isinstance(data, dict):
            raise UnitError(f"the Docker Engine answered {status} for container {ident[:12]}")
        return data

    async def act(self, verb: str, ident: str, grace: float = 0.0) -> None:
        """start or stop (its stop signal, then SIGKILL after ``grace``); already so is no error."""
        query = f"?t={int(grace)}" if verb == "stop" else ""
        status, data = await self.call("POST", f"/containers/{quote(ident)}/{verb}{query}", grace + MARGIN_S)
        if status not in (204, 304):
            message = data.get("message") if isinstance(data, dict) else None
            raise UnitError(f"the Docker Engine refused to {verb} container {ident[:12]} ({status}: "
                            f"{str(message or 'no reason given')[:300]})")


class Systemd:
    """systemctl for the host's system units; each call bounded."""

    def __init__(self, enabled: bool = True, systemctl: str | None = None) -> None:
        self.systemctl = (systemctl or shutil.which("systemctl") or "") if enabled else ""

    def available(self) -> bool:
        return bool(self.systemctl) and os.path.isdir("/run/systemd/system")  # systemd runs this host

    async def run(self, *args: str, timeout: float = CALL_S) -> str:
        try:
            proc = await asyncio.create_subprocess_exec(self.systemctl, *args, stdin=asyncio.subprocess.DEVNULL,
                                                        stdout=asyncio.subprocess.PIPE,
                                                        stderr=asyncio.subprocess.PIPE)
        except OSError as exc:
            raise UnitError(f"systemctl could not be run ({exc.strerror or exc})") from None
        try:
            out, err = await asyncio.wait_for(proc.communicate(), timeout)
        except asyncio.TimeoutError:
            with contextlib.suppress(ProcessLookupError):
                proc.kill()
            await proc.wait()
            raise UnitError(f"systemctl {' '.join(args)} gave no answer within {timeout:g} s") from None
        if proc.returncode != 0:
            raise UnitError(f"systemctl {' '.join(args)} failed: {err.decode(errors='replace').strip()[:300]}")
        return out.decode(errors="replace")

    async def show(self, unit: str) -> dict[str, str]:
        out = await self.run("show", unit, "--property=MainPID,ActiveState,LoadState,NRestarts,ExecMainCode,"
                                           "ExecMainStatus,TimeoutStopUSec,ExecMainStartTimestampMonotonic")
        return dict(line.split("=", 1) for line in out.splitlines() if "=" in line)


@dataclass
class Status:
    running: bool
    pid: int | None
    exit_code: int | None = None
    exit_signal: str | None = None
    grace: float = 10.0  # its supervisor's time between the stop signal and SIGKILL


class HostUnits:
    """Attributes nodes' processes to containers and units, and acts on them for the robot."""

    def __init__(self, report: Callable[..., dict], docker: DockerEngine, systemd: Systemd,
                 proc: Path = Path("/proc"), on_launch: Callable[[], None] = lambda: None) -> None:
        """report(**fields) emits one process fact and returns it; on_launch() once a unit was
        started (or restarted) by its supervisor, before its state is read back."""
        self._report, self.docker, self.systemd, self.proc = report, docker, systemd, proc
        self._on_launch = on_launch
        self._cgroups: OrderedDict[str, HostUnit | None] = OrderedDict()  # cgroup path -> its unit
        self._units: OrderedDict[tuple[str, str], HostUnit] = OrderedDict()  # (robot, name) -> unit
        self._locks: dict[HostUnit, asyncio.Lock] = {}
        # cgroup path -> (when to ask its container's name again, the last wait): the engine did not tell it
        self._asked: dict[str, tuple[float, float]] = {}
        self._own = self._cgroup_of(os.getpid())

    def _cgroup_of(self, pid: int) -> str:
        try:
            return cgroup_path((self.proc / str(pid) / "cgroup").read_text())
        except OSError:
            return ""

    async def identify(self, pid: int) -> HostUnit | None:
        """The container or unit of this host's process, if its supervisor is reachable."""
        path = self._cgroup_of(pid)
        if not path:
            return None
        if path in self._cgroups:
            self._cgroups.move_to_end(path)
            return self._cgroups[path]
        found, unit = unit_in(path, self._own), None
        if found and found[0] == "docker" and self.docker.available():
            asked, now = self._asked.get(path), time.monotonic()
            if asked is not None and now < asked[0]:
                return None
            try:
                name = str((await self.docker.inspect(found[1])).get("Name") or "").lstrip("/")
            except UnitError as exc:
                if asked is None:
                    log.warning("the container of pid %d is not known: %s", pid, exc)
                if len(self._asked) >= LIMIT:
                    self._asked.clear()
                wait = min(ASK_AGAIN_MAX_S, asked[1] * 2) if asked else ASK_AGAIN_FIRST_S
                self._asked[path] = (now + wait, wait)  # asked again then, then less and less often
                return None
            self._asked.pop(path, None)
            name = f"docker:{name}" if protocol.HOST_PROCESS_RE.match(f"docker:{name}") else f"docker:{found[1][:12]}"
            unit = HostUnit("docker", found[1], name)
        elif found and found[0] == "systemd" and self.systemd.available():
            name = f"systemd:{found[1]}"
            unit = HostUnit("systemd", found[1], name) if protocol.HOST_PROCESS_RE.match(name) else None
        elif found:
            return None  # its supervisor is not reachable (yet): looked up again next time
        self._cgroups[path] = unit
        if len(self._cgroups) > LIMIT:
            self._cgroups.popitem(last=False)
        return unit

    def identified(self, pid: int) -> bool:
        """Whether what ``identify`` answers for this process is settled (not to be asked again)."""
        path = self._cgroup_of(pid)
        return not path or path in self._cgroups

    def attribute(self, robot: str, unit: HostUnit) -> None:
        self._units[robot, unit.name] = unit
        self._units.move_to_end((robot, unit.name))
        if len(self._units) > LIMIT:
            self._units.popitem(last=False)

    def known(self, robot: str, name: str) -> HostUnit | None:
        return self._units.get((robot, name))

    def cgroups(self, robot: str) -> dict[str, set[str]]:
        """The robot's containers and units: name -> the cgroups its processes were found in."""
        return {name: {path for path, found in self._cgroups.items() if found == unit}
                for (owner, name), unit in self._units.items() if owner == robot}

    async def control(self, robot: str, name: str, action: str, *, source: str, user_id: int | None = None,
                      vouching: dict | None = None) -> dict:
        """start, stop or restart the unit attributed to one of the robot's nodes; one fact of it.
        LookupError if no unit of that name is attributed to the robot."""
        unit = self._units.get((robot, name))
        if unit is None:
            raise LookupError(name)
        began = time.monotonic()

        def fact(outcome: str, message: str, *, pid: int | None = None, old_pid: int | None = None,
                 ended: Status | None = None) -> dict:
            """ended: the status after the old process's end (its exit code or signal)."""
            return self._report(**(vouching or {}), robot=robot, process=name, supervisor=unit.kind, action=action,
                                outcome=outcome, source=source, user_id=user_id, pid=pid, old_pid=old_pid,
                                exit_code=ended.exit_code if ended else None,
                                exit_signal=ended.exit_signal if ended else None, message=message,
                                took_ms=round((time.monotonic() - began) * 1000, 1))

        what = f"{'Container' if unit.kind == 'docker' else 'Unit'} {name.split(':', 1)[1]} of {robot}"
        async with self._locks.setdefault(unit, asyncio.Lock()):
            try:
                before = await self._status(unit)
                if action == "start" and before.running:
                    return fact("rejected", f"{what} is already running (pid {before.pid}).", pid=before.pid)
                if action == "stop" and not before.running:
                    return fact("rejected", f"{what} is not running.")
                stopped = None
                if action in ("stop", "restart") and before.running:
                    await self._act(unit, "stop", before.grace)
                    stopped = await self._status(unit)
                if action in ("start", "restart"):
                    await self._act(unit, "start", before.grace)
                    self._on_launch()
                after = await self._status(unit)
            except UnitError as exc:
                log.warning("%s: %s failed: %s", what, action, exc)
                return fact("failed", f"{what} was not {_done(action)}: {exc}.")
        old_pid = before.pid if stopped else None
        how = f" (pid {before.pid} {_exit_words(stopped.exit_code, stopped.exit_signal)})" if stopped else ""
        if action == "stop":
            return fact("succeeded", f"{what} stopped{how}.", old_pid=old_pid, ended=stopped)
        if not after.running:
            return fact("failed", f"{what} did not keep running after its start{how}: it "
                        f"{_exit_words(after.exit_code, after.exit_signal)}.", old_pid=old_pid, ended=after)
        log.info("%s %s as pid %s", what, _done(action), after.pid)
        return fact("succeeded", f"{what} {_done(action)} as pid {after.pid}{how}.", pid=after.pid, old_pid=old_pid,
                    ended=stopped)

    async def _status(self, unit: HostUnit) -> Status:
        if unit.kind == "docker":
            data = await self.docker.inspect(unit.ident)
            state = data.get("State") if isinstance(data.get("State"), dict) else {}
            code = state.get("ExitCode") if isinstance(state.get("ExitCode"), int) else None
            sig = SIGNAL_NAMES.get(code - 128) if code is not None and 128 < code < 128 + 65 else None
            stop = (data.get("Config") or {}).get("StopTimeout") if isinstance(data.get("Config"), dict) else None
            return Status(state.get("Running") is True, state.get("Pid") or None, None if sig else code, sig,
                          float(stop) if isinstance(stop, int) and 0 <= stop <= MAX_GRACE_S else 10.0)
        shown = await self.systemd.show(unit.ident)
        if shown.get("LoadState") != "loaded":
            raise UnitError(f"systemd has no unit {unit.ident} loaded ({shown.get('LoadState', 'no answer')})")
        pid = int(shown["MainPID"]) if shown.get("MainPID", "").isdigit() and shown["MainPID"] != "0" else None
        status = int(shown["ExecMainStatus"]) if shown.get("ExecMainStatus", "").isdigit() else None
        killed = shown.get("ExecMainCode") in ("2", "3")  # CLD_KILLED, CLD_DUMPED: the status is a signal
        grace = _usec(shown.get("TimeoutStopUSec", ""))
        return Status(shown.get("ActiveState") in ("active", "reloading", "activating") and pid is not None, pid,
                      None if killed else status, SIGNAL_NAMES.get(status) if killed and status else None,
                      grace)

    async def _act(self, unit: HostUnit, verb: str, grace: float) -> None:
        if unit.kind == "docker":
            await self.docker.act(verb, unit.ident, grace)
        else:
            await self.systemd.run(verb, unit.ident, timeout=grace + MARGIN_S)


def _done(action: str) -> str:
    return {"start": "started", "stop": "stopped", "restart": "restarted"}[action]


def _usec(text: str) -> float:
    """systemctl show's TimeoutStopUSec ("1min 30s", "90s", "500ms", "infinity"), in seconds, at most MAX_GRACE_S."""
    units = {"min": 60.0, "ms": 0.001, "us": 1e-6, "s": 1.0, "h": 3600.0}
    total = sum(float(n) * units[u] for n, u in re.findall(r"(\d+(?:\.\d+)?)(min|ms|us|h|s)", text))
    return min(total, MAX_GRACE_S) if total else (MAX_GRACE_S if text == "infinity" else 90.0)
