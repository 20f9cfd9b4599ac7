"""Several daphne processes behind one listening socket (``LIFECYCLE_WEB_PROCESSES``).

One daphne runs Python in one core at a time. Under a control room's load (50 open pages, 100
API requests/s) it spends most of a core and answers late while the machine's other cores
wait; docs/performance.md has the figures. With N > 1, this process binds the address once and
starts N daphne processes that all accept from that socket (the kernel hands each new
connection to one of them), so a second core serves pages too. Nothing of the site is kept in
one process that the others need: sessions, audit and state live in the database, pushes go
through the Channels layer in Redis (each page's socket is served by the process that
accepted it), and what a process keeps in memory is a cache of a second or less.

This process only supervises: it passes SIGTERM/SIGINT on and waits for them (bounded), starts
a process again that ended on its own (after a pause that grows while they keep ending at
once), and gives up, ending with an error, when they end at once RESTART_LIMIT times in a row.
"""
from __future__ import annotations

import logging
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field

from ros_gateway.shared.child_process import die_with_parent

log = logging.getLogger("lifecycle_site.web")

STOP_WAIT_S = 15.0  # how long the processes get to finish their answers when told to stop
EARLY_EXIT_S = 10.0  # a process that ends sooner after its start than this ended "at once"
RESTART_LIMIT = 5  # ... that many times in a row: the site cannot start (bad settings, say)
MAX_RESTART_PAUSE_S = 8.0
BACKLOG = 1024


class LaunchRefused(SystemExit):
    """The options cannot be served by several processes; the message says what to change."""


@dataclass
class Listener:
    """Where to listen (daphne's -b/--bind and -p/--port) and the options the processes get."""

    host: str
    port: int
    passed: list[str] = field(default_factory=list)


def split_options(argv: list[str]) -> Listener:
    """Take the address out of daphne's options; the rest goes to each process unchanged."""
    host, port, passed = "127.0.0.1", 8000, []
    options = iter(argv)
    for option in options:
        name, has_value, value = option.partition("=")
        if name in ("-b", "--bind", "-p", "--port"):
            if not has_value:
                value = next(options, "")
            if name in ("-b", "--bind"):
                host = value
            else:
                try:
                    port = int(value)
                except ValueError:
                    raise LaunchRefused(f"daphne's port {value!r} is not a number.") from None
        elif name in ("-u", "--unix-socket", "--fd", "-e", "--endpoint"):
            raise LaunchRefused(
                f"LIFECYCLE_WEB_PROCESSES above 1 serves one TCP address (-b HOST -p PORT); {name} is not "
                "supported with it. Leave LIFECYCLE_WEB_PROCESSES unset (one process) for that.")
        else:
            passed.append(option)
    if ":" in host.strip("[]"):
        raise LaunchRefused(f"LIFECYCLE_WEB_PROCESSES above 1 listens on IPv4 only; {host!r} is IPv6. Bind to an "
                            "IPv4 address (0.0.0.0 for all) or leave LIFECYCLE_WEB_PROCESSES unset.")
    return Listener(host, port, passed)


def bind(listener: Listener) -> socket.socket:
    try:
        server = socket.create_server((listener.host, listener.port), backlog=BACKLOG)
    except OSError as exc:
        raise LaunchRefused(f"Cannot listen on {listener.host}:{listener.port}: {exc.strerror or exc}.") from None
    server.set_inheritable(True)
    return server


class Processes:
    """N daphne processes on one socket, kept running until told to stop."""

    def __init__(self, count: int, listener: Listener, environ: dict[str, str]) -> None:
        self.count, self.listener = count, listener
        self.environ = {**environ, "LIFECYCLE_WEB_PROCESSES": "1"}  # each one serves, none supervises
        self.socket = bind(listener)
        self.children: list[subprocess.Popen | None] = [None] * count
        self.started: list[float] = [0.0] * count
        self.early_exits = 0
        self.stopping: int | None = None  # the signal we were told to stop with

    def command(self) -> list[str]:
        return [sys.executable, "-m", "lifecycle_site.serve", "--fd", str(self.socket.fileno()),
                *self.listener.passed]

    def start(self, slot: int) -> None:
        self.children[slot] = subprocess.Popen(self.command(), env=self.environ, pass_fds=(self.socket.fileno(),),
                                               preexec_fn=die_with_parent())
        self.started[slot] = time.monotonic()

    def run(self) -> int:
        for signum in (signal.SIGTERM, signal.SIGINT):
            signal.signal(signum, self._stop)
        log.warning("serving http://%s:%d/ with %d daphne processes", self.listener.host, self.listener.port,
                    self.count)
        for slot in range(self.count):
            self.start(slot)
        try:
            while self.stopping is None:
                self._look_after()
                time.sleep(0.2)
            return self._wait_for_all()
        finally:
            self._kill_what_is_left()
            self.socket.close()

    def _stop(self, signum: int, _frame) -> None:
        self.stopping = signum

    def _look_after(self) -> None:
        for slot, child in enumerate(self.children):
            if child is None or child.poll() is None:
                continue
            lasted = time.monotonic() - self.started[slot]
            self.early_exits = self.early_exits + 1 if lasted < EARLY_EXIT_S else 0
            if self.early_exits >= RESTART_LIMIT:
                log.error("daphne ended %d times in a row within %.0f s of its start (last: exit status %s); "
                          "stopping the site", self.early_exits, EARLY_EXIT_S, child.returncode)
                self.stopping = signal.SIGTERM
                self.exit_status = 1
                return
            pause = min(MAX_RESTART_PAUSE_S, 0.5 * 2 ** self.early_exits) if self.early_exits else 0.0
            log.error("daphne process %d ended (exit status %s after %.0f s); starting it again%s", child.pid,
                      child.returncode, lasted, f" in {pause:.1f} s" if pause else "")
            self.children[slot] = None
            self._sleep_unless_stopped(pause)
            if self.stopping is None:
                self.start(slot)

    def _sleep_unless_stopped(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while self.stopping is None and time.monotonic() < end:
            time.sleep(0.1)

    exit_status = 0

    def _wait_for_all(self) -> int:
        running = [child for child in self.children if child is not None and child.poll() is None]
        for child in running:
            child.send_signal(self.stopping or signal.SIGTERM)
        end = time.monotonic() + STOP_WAIT_S
        for child in running:
            try:
                child.wait(max(0.0, end - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
        return self.exit_status

    def _kill_what_is_left(self) -> None:
        for child in self.children:
            if child is not None and child.poll() is None:
                log.error("daphne process %d did not stop within %.0f s; killed", child.pid, STOP_WAIT_S)
                child.kill()
                child.wait(5)


def serve(count: int, argv: list[str], environ: dict[str, str]) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    return Processes(count, split_options(argv), environ).run()
