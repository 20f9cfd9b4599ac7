"""`make demo` killed hard (SIGKILL: no chance to clean up) leaves nothing running behind it:
its Redis, gateway, demo robots and daphne all end with it."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil

from tests import stack

CHILDREN = {  # what run_demo starts, told apart by a word of their command line
    "redis-server": 1,
    "ros_gateway": 1,
    "ros_gateway.demo.robot": 4,
    "lifecycle_site.serve": 1,
}


def _kind(process: psutil.Process) -> str:
    words = process.cmdline()
    for kind in ("ros_gateway.demo.robot", "lifecycle_site.serve", "ros_gateway"):
        if kind in words:
            return kind
    return "redis-server" if "redis-server" in " ".join(words[:1]) else " ".join(words)


def _of_data_dir(data_dir: str) -> list[psutil.Process]:
    """Every running process whose environment points at this demo's data dir."""
    found = []
    for process in psutil.process_iter():
        try:
            if process.pid != os.getpid() and process.environ().get("LIFECYCLE_DATA_DIR") == data_dir:
                found.append(process)
        except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
            continue
    return found


def _running(processes: list[psutil.Process]) -> list[psutil.Process]:
    """The ones still running (a zombie waiting for its new parent to reap it is gone)."""
    left = []
    for process in processes:
        try:
            if process.is_running() and process.status() != psutil.STATUS_ZOMBIE:
                left.append(process)
        except psutil.NoSuchProcess:
            continue
    return left


def _describe(processes: list[psutil.Process]) -> str:
    lines = []
    for process in processes:
        try:
            lines.append(f"pid {process.pid}: {' '.join(process.cmdline())}")
        except psutil.Error:
            lines.append(f"pid {process.pid}")
    return "\n".join(lines)


def test_sigkill_of_the_demo_ends_all_its_processes(tmp_path: Path):
    data_dir = str(tmp_path / "demo-data")
    env = dict(os.environ)
    for name in ("DATABASE_URL", "DJANGO_ALLOW_ASYNC_UNSAFE", "PYTHONUNBUFFERED"):  # own SQLite; output to a file
        env.pop(name, None)
    env.update(
        DJANGO_SETTINGS_MODULE="lifecycle_site.settings",
        LIFECYCLE_DATA_DIR=data_dir,
        REDIS_URL=f"redis://127.0.0.1:{stack.free_port()}/0",  # nothing answers: run_demo starts one
        DEMO_DOMAIN_AGV1=str(stack.domain(27)),
        DEMO_DOMAIN_AGV2=str(stack.domain(28)),
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
    )  # output to a file, as `make demo > demo.log`: the URL and login must be there all the same
    output = tmp_path / "run_demo.out"
    with open(output, "wb") as out:
        demo = subprocess.Popen(
            [sys.executable, "manage.py", "run_demo", "--port", str(stack.free_port())],
            cwd=stack.ROOT, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
        )
    children: list[psutil.Process] = []
    try:
        stack.wait_for(
            lambda: "Lifecycle manager running at" in output.read_text() or demo.poll() is not None,
            90, "run_demo to print its URL",
        )
        assert demo.poll() is None, f"run_demo ended on start:\n{output.read_text()}"

        def all_started() -> bool:
            children[:] = psutil.Process(demo.pid).children(recursive=True)
            kinds = [_kind(child) for child in children]
            return all(kinds.count(kind) == count for kind, count in CHILDREN.items())

        stack.wait_for(all_started, 20, f"run_demo's children {CHILDREN}", tolerate=(psutil.Error,))

        started = time.monotonic()
        os.kill(demo.pid, signal.SIGKILL)  # the run_demo process alone, not its children
        demo.wait(5)
        deadline = started + 5
        while _running(children) and time.monotonic() < deadline:
            time.sleep(0.1)
        left = _running(children)
        assert not left, f"still running 5 s after run_demo was killed:\n{_describe(left)}"
        stray = _running(_of_data_dir(data_dir))
        assert not stray, f"processes of the killed demo's data dir still running:\n{_describe(stray)}"
    finally:
        if demo.poll() is None:
            demo.kill()
            demo.wait(5)
        for process in _running(children + _of_data_dir(data_dir)):
            try:
                process.kill()
            except psutil.NoSuchProcess:
                pass
