"""A small process supervisor for the demo: starts children, respawns those that die
(as systemd, compose restart policies or launch's respawn would), stops them all at the end."""
from __future__ import annotations

import os
import signal
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

from ros_gateway.shared.child_process import die_with_parent

RESPAWN_DELAY_S = 2.0


@dataclass
class Child:
    name: str
    argv: list[str]
    log_path: Path
    env: dict[str, str] = field(default_factory=dict)
    respawn: bool = True
    process: subprocess.Popen | None = None
    died_at: float | None = None
    restarts: int = 0

    def start(self) -> None:
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        log = open(self.log_path, "ab")
        self.process = subprocess.Popen(
            self.argv,
            stdout=log,
            stderr=subprocess.STDOUT,
            env={**os.environ, **self.env},
            start_new_session=True,  # Ctrl-C in the terminal reaches us, and we stop the children
            preexec_fn=die_with_parent(),  # SIGTERM when the supervisor dies, even by SIGKILL
        )
        log.close()
        self.died_at = None


class Supervisor:
    def __init__(self) -> None:
        self.children: list[Child] = []

    def add(self, child: Child) -> Child:
        self.children.append(child)
        child.start()
        return child

    def watch_once(self, report) -> None:
        """Respawn children that exited; ``report(text)`` tells the user."""
        now = time.monotonic()
        for child in self.children:
            code = child.process.poll() if child.process else None
            if code is None:
                continue
            if child.died_at is None:
                child.died_at = now
                report(f"{child.name} exited with code {code}" + (", restarting it" if child.respawn else ""))
            if child.respawn and now - child.died_at >= RESPAWN_DELAY_S:
                child.restarts += 1
                child.start()

    def stop(self, timeout: float = 10.0) -> None:
        for child in reversed(self.children):
            if child.process and child.process.poll() is None:
                os.killpg(child.process.pid, signal.SIGTERM)
        deadline = time.monotonic() + timeout
        for child in self.children:
            if child.process is None:
                continue
            try:
                child.process.wait(max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                os.killpg(child.process.pid, signal.SIGKILL)
                child.process.wait()
