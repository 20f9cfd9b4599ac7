"""The gateway as the supervisor of a robot's processes (launch profiles): it starts them, hands their output on,
reports their exits, respawns them with a bounded back-off, and starts, stops and restarts them on request. Each
has its own process group (a stop reaches what it started too, as with a launch file) and ends with the gateway.
"""
from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import shlex
import shutil
import signal
import subprocess
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Callable

from ros_gateway import leftovers, tasks
from ros_gateway.launch_profile import LaunchProfile
from ros_gateway.shared.child_process import die_with_parent

log = logging.getLogger(__name__)

MIN_UPTIME_S, MAX_RESPAWN_DELAY_S = 10.0, 30.0  # an exit this soon after its start doubles the back-off, up to
EARLY_EXIT_S = 0.5  # a process ending this soon with a non-zero status did not start
LINE_LIMIT = 4096  # bytes of one output line handed on; the rest is dropped and the line marked "…"
DRAIN_S, KILL_WAIT_S, CLOSE_MARGIN_S = 1.0, 3.0, 5.0  # bounds: output after the end; the end after SIGKILL; close()
SIGNAL_NAMES = {int(sig): sig.name for sig in signal.Signals}
Process = asyncio.subprocess.Process


class UnknownProcess(LookupError):
    """A (robot, process) this supervisor has no launch profile for."""


@dataclass
class _Act:  # who asked for an action (into its fact), and since when
    source: str
    user_id: int | None = None
    vouching: dict | None = None
    t0: float = field(default_factory=time.monotonic)


class _Supervised:
    """One launch profile and the process running it, if any."""

    def __init__(self, profile: LaunchProfile) -> None:
        self.profile, self.lock, self.state = profile, asyncio.Lock(), "stopped"
        self.who = f"{profile.name} on {profile.robot}"
        self.proc: Process | None = None
        self.done_with: Process | None = None  # its end was asked for, or is reported already
        self.gone: asyncio.Future | None = None  # done when that process has ended (_gone)
        self.watcher: asyncio.Future | None = None
        self.respawner: asyncio.Future | None = None
        self.started_at: str | None = None
        self.last_exit: dict | None = None
        self.last_pid: int | None = None
        self.exits: list[float] = []  # when it ended unasked, within failure_window (monotonic)
        self.started_mono, self.restarts, self.streak = 0.0, 0, 0  # streak: quick exits in a row (the back-off)

    def ended(self, code: int | None) -> str:
        """Keeps the end (status() shows it); how it ended, for a message."""
        sig = None if code is None or code >= 0 else SIGNAL_NAMES.get(-code, f"signal {-code}")
        self.last_exit = {"code": None if sig else code, "signal": sig, "at": datetime.now(timezone.utc).isoformat()}
        return f"was ended by {sig}" if sig else f"exited with status {code}" if code is not None else "ended"


class Supervisor:
    def __init__(self, report: Callable[..., dict], on_output: Callable[[str, str, str, str], None],
                 gateway: str = "", on_launch: Callable[[], None] = lambda: None) -> None:
        """report(**fields) emits one fact and returns it; on_output(robot, name, stream, line) gets each line;
        ``gateway``: its name, marked on every process it starts (leftovers.py); on_launch() as soon as a process
        was started (its nodes may appear before it counts as started, EARLY_EXIT_S later)."""
        self._report, self._on_output, self.gateway, self._on_launch = report, on_output, gateway, on_launch
        self._procs: dict[tuple[str, str], _Supervised] = {}
        self._applying, self._closed = asyncio.Lock(), False

    async def apply(self, profiles: list[LaunchProfile]) -> None:
        """The profiles wanted now (all robots): new ones started, others stopped, changed ones restarted."""
        async with self._applying:
            wanted = {(profile.robot, profile.name): profile for profile in profiles}
            jobs = [self._locked(*key, self._retire, _Act("config")) for key in self._procs if key not in wanted]
            for key, profile in wanted.items():
                if (p := self._procs.get(key)) is None:
                    self._procs[key] = _Supervised(profile)
                    jobs.append(self._locked(*key, self._start, _Act("config")))
                elif p.profile != profile:
                    jobs.append(self._locked(*key, self._restart, _Act("config"), profile))
            for result in await asyncio.gather(*jobs, return_exceptions=True):
                if isinstance(result, Exception):
                    log.error("applying the launch profiles failed", exc_info=result)

    async def start(self, robot: str, name: str, *, source: str, user_id: int | None = None,
                    vouching: dict | None = None) -> dict:
        return await self._locked(robot, name, self._start, _Act(source, user_id, vouching))

    async def stop(self, robot: str, name: str, *, source: str, user_id: int | None = None,
                   vouching: dict | None = None) -> dict:
        return await self._locked(robot, name, self._stop, _Act(source, user_id, vouching))

    async def restart(self, robot: str, name: str, *, source: str, user_id: int | None = None,
                      vouching: dict | None = None) -> dict:
        return await self._locked(robot, name, self._restart, _Act(source, user_id, vouching))

    def status(self) -> list[dict]:
        now = time.monotonic()
        return [{"robot": p.profile.robot, "name": p.profile.name, "state": p.state, "pid": p.proc and p.proc.pid,
                 "started": p.started_at if p.proc else None,
                 "uptime_s": round(now - p.started_mono, 1) if p.proc else None, "restarts": p.restarts,
                 "last_exit": dict(p.last_exit) if p.last_exit else None, "respawn": p.profile.respawn,
                 "command": shlex.join((p.profile.command, *p.profile.args))} for p in self._procs.values()]

    def pids(self) -> dict[int, tuple[str, str]]:
        return {p.proc.pid: (p.profile.robot, p.profile.name) for p in self._procs.values()
                if p.proc is not None and p.proc.returncode is None}

    async def close(self) -> None:
        """Stop every process (stop_signal, grace, then SIGKILL), bounded; reports nothing."""
        self._closed, procs = True, dict(self._procs)
        bound = max((p.profile.stop_grace for p in procs.values()), default=0.0) + CLOSE_MARGIN_S
        try:
            await asyncio.wait_for(asyncio.gather(*(self._locked(*key, self._retire, None) for key in procs),
                                                  return_exceptions=True), bound)
        except asyncio.TimeoutError:
            log.warning("processes still stopping after %.0f s: killing them", bound)
        for pid in [p.proc.pid for p in procs.values() if p.proc is not None]:
            _signal_group(pid, signal.SIGKILL)

    async def _locked(self, robot: str, name: str, action: Callable, act: _Act, *args: object) -> dict | None:
        if (p := self._procs.get((robot, name))) is not None:
            async with p.lock:
                if self._procs.get((robot, name)) is p:  # not removed while it waited for the lock
                    return await action(p, act, *args)
        raise UnknownProcess(f"no process {name!r} is supervised on robot {robot!r}")

    async def _start(self, p: _Supervised, act: _Act, action: str = "start", note: str = "") -> dict:
        if action == "start" and p.proc is not None:
            return self._fact(p, act, "start", "rejected", f"{p.who} is already running (pid {p.proc.pid}).",
                              pid=p.proc.pid)
        if action != "respawn":  # asked for: the failures and the back-off count from zero, a respawn is off
            p.exits, p.streak, p.respawner = [], 0, None
        old_pid = p.last_pid if action == "respawn" or note else None  # the one it follows (a restart's: stopped)
        error, proc = await self._launch(p)
        if error is not None:
            return self._down(p, act, action, "failed", f"{p.who} did not start{note}: {error}",
                              time.monotonic() - p.started_mono if proc else 0.0, old_pid=old_pid, ended=bool(proc))
        p.restarts += action != "start"
        verb = {"start": "started", "restart": "restarted", "respawn": "started again"}[action]
        log.info("%s %s as pid %d%s", p.who, verb, proc.pid, note)
        fact = self._fact(p, act, action, "succeeded", f"{p.who} {verb} as pid {proc.pid}{note}.", pid=proc.pid,
                          old_pid=old_pid)
        if p.watcher.done():  # ended with status 0 within EARLY_EXIT_S: an exit like any
            self._exited(p, proc)
        return fact

    async def _stop(self, p: _Supervised, act: _Act | None) -> dict:
        proc, how = p.proc, "it was waiting to be started again"
        if proc is None and p.state != "backing_off":
            return self._fact(p, act, "stop", "rejected", f"{p.who} is not running.")
        if proc is not None:
            how = await self._halt(p, proc)
        p.state = "stopped"
        log.info("%s stopped: %s", p.who, how)
        return self._fact(p, act, "stop", "succeeded", f"{p.who} stopped: {how}.", old_pid=proc and proc.pid,
                          ended=proc is not None)

    async def _restart(self, p: _Supervised, act: _Act, profile: LaunchProfile | None = None) -> dict | None:
        if profile is not None and p.state == "stopped":  # from apply(): stopped on request, it stays so
            p.profile = profile
            return None
        note = f" (pid {old.pid} stopped: {await self._halt(p, old)})" if (old := p.proc) else ""
        p.profile = profile or p.profile
        return await self._start(p, act, "restart", note)

    async def _retire(self, p: _Supervised, act: _Act | None) -> None:
        if p.proc is not None or p.state == "backing_off":
            await self._stop(p, act)
        del self._procs[p.profile.robot, p.profile.name]

    async def _respawn(self, p: _Supervised, delay: float) -> None:
        await asyncio.sleep(delay)
        async with p.lock:
            if p.state == "backing_off" and p.respawner is asyncio.current_task():  # not stopped nor replaced
                await self._start(p, _Act("supervisor"), "respawn")

    async def _launch(self, p: _Supervised) -> tuple[str | None, Process | None]:
        """(None, the running process), or why it did not start (and the process if it ended at once)."""
        env = {**_inherited(), "PYTHONUNBUFFERED": os.environ.get("PYTHONUNBUFFERED", "1"), **dict(p.profile.env),
               leftovers.MARK: leftovers.mark(self.gateway, p.profile.robot, p.profile.name)}
        error, program = _program(profile := p.profile, env.get("PATH", os.defpath))
        if error is not None or self._closed:
            return error or "the gateway is stopping", None
        p.state = "starting"
        try:
            proc = await asyncio.create_subprocess_exec(
                program, *profile.args, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                cwd=profile.cwd, env=env, limit=LINE_LIMIT, start_new_session=True,
                preexec_fn=die_with_parent())
        except (OSError, subprocess.SubprocessError) as exc:
            return f"{profile.command} could not be run ({getattr(exc, 'strerror', None) or exc})", None
        p.proc, p.gone, p.done_with, p.last_pid = proc, _gone(proc), None, proc.pid
        self._on_launch()
        p.started_at, p.started_mono = datetime.now(timezone.utc).isoformat(), time.monotonic()
        readers = [tasks.spawn(self._read(profile, name, pipe)) for name, pipe in
                   (("stdout", proc.stdout), ("stderr", proc.stderr))]
        p.watcher = tasks.spawn(self._watch(p, proc, p.gone, readers))
        await asyncio.wait([p.watcher], timeout=EARLY_EXIT_S)  # done: it has ended, its output read
        if p.watcher.done() and proc.returncode != 0:
            p.done_with, p.proc = proc, None
            return f"it {p.ended(proc.returncode)} within {_s(time.monotonic() - p.started_mono)} of its start", proc
        p.state = "running"
        return None, proc

    async def _watch(self, p: _Supervised, proc: Process, gone: asyncio.Future, readers: list[asyncio.Future]) -> None:
        """At its end: its group killed (it holds its pipes), its output read, the end reported if nobody did."""
        await gone
        _signal_group(proc.pid, signal.SIGKILL)
        _, pending = await asyncio.wait([*readers, asyncio.ensure_future(proc.wait())], timeout=DRAIN_S)
        for task in pending:  # a process outside its group holds its pipes
            task.cancel()
        if p.proc is proc and p.done_with is not proc and p.state != "starting" and not self._closed:
            self._exited(p, proc)

    def _exited(self, p: _Supervised, proc: Process) -> None:
        p.done_with, p.proc, ran = proc, None, time.monotonic() - p.started_mono
        self._down(p, _Act("supervisor"), "exited", "succeeded" if proc.returncode == 0 else "failed",
                   f"{p.who} {p.ended(proc.returncode)} after {_s(ran)}", ran, old_pid=proc.pid, ended=True)

    def _down(self, p: _Supervised, act: _Act, action: str, outcome: str, message: str, ran: float,
              **fields: object) -> dict:
        """Reports an end not asked for (or a failed start); then a respawn after the back-off, or giving up."""
        profile, now, delay, count = p.profile, time.monotonic(), None, 0
        window, p.state, suffix = _s(profile.failure_window), "exited", "; respawn is off"
        if profile.respawn and not self._closed:
            p.exits = [*(t for t in p.exits if t >= now - profile.failure_window), now]
            if (count := len(p.exits)) >= profile.max_failures:
                p.state, suffix = "given_up", f"; that is {count} times within {window}: it is not started again"
            else:
                p.streak = p.streak + 1 if ran < MIN_UPTIME_S else 0
                base = profile.respawn_delay
                delay = max(base, min(base * 2 ** min(max(p.streak - 1, 0), 16), MAX_RESPAWN_DELAY_S))
                p.state, suffix = "backing_off", (f"; starting it again in {_s(delay)} (respawn {count} of "
                                                  f"{profile.max_failures - 1} within {window})")
        log.warning("%s%s", message, suffix)
        fact = self._fact(p, act, action, outcome, f"{message}{suffix}.", **fields)
        if p.state == "given_up":
            self._fact(p, _Act("supervisor"), "gave_up", "failed", f"{p.who} ended {count} times within {window}; "
                       "it is not started again until someone starts it.", old_pid=p.last_pid)
        elif delay is not None:
            p.respawner = tasks.spawn(self._respawn(p, delay))
        return fact

    async def _halt(self, p: _Supervised, proc: Process) -> str:
        """stop_signal to its group, up to stop_grace, then SIGKILL; how that went."""
        profile, name, gone = p.profile, SIGNAL_NAMES[p.profile.stop_signal], p.gone
        p.done_with, p.state, began, how = proc, "stopping", time.monotonic(), "it had ended already"
        if not gone.done():
            _signal_group(proc.pid, profile.stop_signal)
            await asyncio.wait([gone], timeout=profile.stop_grace)
            how = f"{name}, ended after {_s(time.monotonic() - began)}"
            if not gone.done():
                how = f"{name}, then SIGKILL after {_s(profile.stop_grace)} without ending"
        _signal_group(proc.pid, signal.SIGKILL)  # the rest of its group (the watcher does so too), or all of it
        await asyncio.wait([p.watcher], timeout=KILL_WAIT_S)  # its end seen, its output read to the end
        p.proc = None
        p.ended(proc.returncode)
        return how

    async def _read(self, profile: LaunchProfile, stream: str, reader: asyncio.StreamReader) -> None:
        """Hands each line of one pipe on; of a line longer than LINE_LIMIT bytes the rest is dropped."""
        skipping = False  # the rest of a line too long
        while True:
            try:
                raw, cut = await reader.readuntil(b"\n"), False
            except asyncio.IncompleteReadError as exc:  # the end (its last line may have no newline)
                if not (raw := exc.partial):
                    return
                cut = False
            except (asyncio.LimitOverrunError, ValueError):  # LINE_LIMIT bytes and no newline: the buffer is full
                raw, cut = await reader.read(LINE_LIMIT), True
            try:
                if not skipping:
                    line = raw.removesuffix(b"\n").removesuffix(b"\r").decode("utf-8", "replace") + "…" * cut
                    self._on_output(profile.robot, profile.name, stream, line)
            except Exception:
                log.exception("the output of %s on %s could not be handed on", profile.name, profile.robot)
            skipping = cut

    def _fact(self, p: _Supervised, act: _Act | None, action: str, outcome: str, message: str, *,
              pid: int | None = None, old_pid: int | None = None, ended: bool = False) -> dict:
        """One fact (ended: with the last exit's status or signal), unless act is None."""
        last = p.last_exit if ended and p.last_exit else {"code": None, "signal": None}
        return {} if act is None else self._report(**{
            **(act.vouching or {}), "robot": p.profile.robot, "process": p.profile.name, "action": action,
            "outcome": outcome, "source": act.source, "user_id": act.user_id, "pid": pid, "old_pid": old_pid,
            "exit_code": last["code"], "exit_signal": last["signal"], "message": message,
            "took_ms": round((time.monotonic() - act.t0) * 1000, 1)})


def _program(profile: LaunchProfile, path: str) -> tuple[str | None, str]:
    """(None, the executable to run), or (why there is none, "")."""
    command, cwd = profile.command, profile.cwd
    if cwd is not None and not os.path.isdir(cwd):
        return f"its working directory {cwd} does not exist", ""
    if "/" not in command:
        found = shutil.which(command, path=path)
        return (None, found) if found else (f"no executable named {command} was found on PATH", "")
    full = os.path.join(cwd or "", command)  # a relative path is relative to cwd, as exec sees it
    if not os.path.isfile(full):
        return f"the executable {command} does not exist", ""
    return (None, command) if os.access(full, os.X_OK) else (f"{command} is not executable", "")


def _gone(proc: Process) -> asyncio.Future:
    """Done when the process has ended: a pidfd turns readable. (proc.wait() waits for its pipes too.)"""
    loop, gone = asyncio.get_running_loop(), asyncio.get_running_loop().create_future()
    try:
        fd = os.pidfd_open(proc.pid)
    except (AttributeError, OSError):  # not Linux (5.3 or later): proc.wait() it is
        return tasks.spawn(proc.wait())
    loop.add_reader(fd, lambda: gone.done() or gone.set_result(None))
    gone.add_done_callback(lambda _: (loop.remove_reader(fd), os.close(fd)))
    return gone


# The gateway's own settings and credentials (its Redis URL holds its password): not the business
# of the processes it runs, which get the rest of its environment (ROS_*, PATH, ...) and their profile's.
PRIVATE_PREFIXES, PRIVATE_NAMES = ("LIFECYCLE_", "DJANGO_"), {"REDIS_URL", "DATABASE_URL"}


def _inherited() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k not in PRIVATE_NAMES and not k.startswith(PRIVATE_PREFIXES)}


def _signal_group(pid: int, sig: int) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):  # the group has ended
        os.killpg(pid, sig)


def _s(seconds: float) -> str:
    if seconds >= 60 and seconds % 60 == 0:
        return f"{seconds / 60:g} min"
    return f"{seconds:.1f} s" if seconds >= 1 else f"{seconds:.2f} s"
