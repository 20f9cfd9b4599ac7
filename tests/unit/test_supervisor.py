"""The gateway's process supervisor with real child processes: output captured, exits reported and
respawned with a bounded back-off, giving up on a crash loop, stops escalating to SIGKILL and
reaching the process's own children, nothing left running after close()."""
from __future__ import annotations

import asyncio
import re
import shlex
import sys
import time
from pathlib import Path

import pytest

from ros_gateway.launch_profile import LaunchProfile
from ros_gateway.supervisor import LINE_LIMIT, Supervisor, UnknownProcess

ROBOT = "agv-1"
SLEEPER = "import time\nwhile True: time.sleep(0.1)"
IGNORES_TERM = ("import signal, time\nsignal.signal(signal.SIGTERM, signal.SIG_IGN)\nprint('ready', flush=True)\n"
                "while True: time.sleep(0.1)")


def python(name: str, code: str, **options) -> LaunchProfile:
    return LaunchProfile(ROBOT, name, sys.executable, ("-c", code), **options)


def shell(name: str, script: str, **options) -> LaunchProfile:
    return LaunchProfile(ROBOT, name, "/bin/sh", ("-c", script), **options)


def alive(pid: int) -> bool:
    """Whether the process exists and is no zombie."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat[stat.rindex(")") + 2] != "Z"


class Rig:
    """A supervisor whose facts and output lines are kept in lists."""

    def __init__(self) -> None:
        self.facts: list[dict] = []
        self.lines: list[tuple[str, str, str]] = []
        self.supervisor = Supervisor(self.report, self.output)

    def report(self, **fields) -> dict:
        self.facts.append(fields)
        return fields

    def output(self, robot: str, name: str, stream: str, line: str) -> None:
        assert robot == ROBOT
        self.lines.append((name, stream, line))

    def of(self, name: str, action: str | None = None) -> list[dict]:
        return [f for f in self.facts if f["process"] == name and action in (None, f["action"])]

    def state(self, name: str) -> dict:
        return next(row for row in self.supervisor.status() if row["name"] == name)

    async def until(self, condition, timeout: float = 3.0) -> None:
        deadline = time.monotonic() + timeout
        while not condition():
            if time.monotonic() > deadline:
                lines = [(name, stream, line[:100]) for name, stream, line in self.lines]
                raise AssertionError(f"not within {timeout} s; facts: {self.facts}, lines: {lines}")
            await asyncio.sleep(0.02)


def run(scenario, *profiles: LaunchProfile) -> None:
    """The scenario with a rig whose supervisor has the profiles applied; every process ends with it."""
    async def main() -> None:
        rig = Rig()
        try:
            await rig.supervisor.apply(list(profiles))
            await scenario(rig)
        finally:
            pids = list(rig.supervisor.pids())
            await rig.supervisor.close()
            assert not [pid for pid in pids if alive(pid)]
    asyncio.run(main())


def test_start_runs_the_command_and_hands_on_stdout_and_stderr_lines():
    code = ("import os, sys\nprint('hello', os.environ['GREETING'], os.environ['PYTHONUNBUFFERED'])\n"
            "sys.stderr.buffer.write('ünïcode '.encode() + b'\\xff\\n')\nsys.stderr.flush()\n"
            "sys.stdout.write('no newline at the end')\n"
            "import time\ntime.sleep(30)")

    async def scenario(rig: Rig) -> None:
        started = rig.of("talker")
        assert [(f["action"], f["outcome"], f["source"]) for f in started] == [("start", "succeeded", "config")]
        row = rig.state("talker")
        assert row["state"] == "running" and row["pid"] == started[0]["pid"] and rig.supervisor.pids() == {
            row["pid"]: (ROBOT, "talker")}
        assert row["started"].endswith("+00:00") and row["uptime_s"] >= 0.4 and row["restarts"] == 0
        assert row["command"] == shlex.join([sys.executable, "-c", code])  # the environment not shown
        await rig.until(lambda: len(rig.lines) == 2)
        assert sorted(rig.lines) == [("talker", "stderr", "ünïcode \ufffd"), ("talker", "stdout", "hello hi 1")]
        stopped = await rig.supervisor.stop(ROBOT, "talker", source="api", user_id=7, vouching={"request": "r-1"})
        assert stopped["outcome"] == "succeeded" and stopped["old_pid"] == row["pid"] and stopped["user_id"] == 7
        assert stopped["request"] == "r-1" and stopped["exit_signal"] == "SIGTERM"
        assert "SIGKILL" not in stopped["message"]
        assert ("talker", "stdout", "no newline at the end") in rig.lines  # read to the end
        assert rig.state("talker")["state"] == "stopped" and rig.supervisor.pids() == {}
        assert not alive(row["pid"])

    run(scenario, python("talker", code, env=(("GREETING", "hi"),)))


def test_a_stop_escalates_to_sigkill_when_sigterm_is_ignored_and_says_so():
    async def scenario(rig: Rig) -> None:
        await rig.until(lambda: rig.lines)
        pid = rig.state("stubborn")["pid"]
        fact = await rig.supervisor.stop(ROBOT, "stubborn", source="api")
        assert fact["outcome"] == "succeeded" and fact["exit_signal"] == "SIGKILL" and fact["old_pid"] == pid
        assert "SIGTERM, then SIGKILL after 0.50 s without ending" in fact["message"]
        assert 500 <= fact["took_ms"] < 2500 and not alive(pid)
        assert rig.state("stubborn")["last_exit"]["signal"] == "SIGKILL"
        await asyncio.sleep(0.2)
        assert not rig.of("stubborn", "exited") and not rig.of("stubborn", "respawn")  # asked for: no respawn

    run(scenario, python("stubborn", IGNORES_TERM, stop_grace=0.5))


def test_a_crash_is_reported_once_and_respawned_with_a_new_pid():
    async def scenario(rig: Rig) -> None:
        first = rig.state("crasher")["pid"]
        await rig.until(lambda: rig.of("crasher", "respawn"))
        exited, respawn = rig.of("crasher", "exited"), rig.of("crasher", "respawn")
        assert len(exited) == 1 and len(respawn) == 1
        assert exited[0]["exit_code"] == 3 and exited[0]["exit_signal"] is None and exited[0]["old_pid"] == first
        assert exited[0]["source"] == "supervisor" and exited[0]["outcome"] == "failed"
        assert re.fullmatch(r"crasher on agv-1 exited with status 3 after \d\.\d+ s; starting it again in 0\.05 s "
                            r"\(respawn 1 of 4 within 5 min\)\.", exited[0]["message"])
        assert respawn[0]["outcome"] == "succeeded" and respawn[0]["source"] == "supervisor"
        assert respawn[0]["old_pid"] == first and respawn[0]["pid"] not in (None, first)
        row = rig.state("crasher")
        assert row["pid"] == respawn[0]["pid"] and row["restarts"] == 1 and row["last_exit"]["code"] == 3

    run(scenario, python("crasher", "import sys, time\ntime.sleep(0.6)\nsys.exit(3)", respawn_delay=0.05))


def test_a_process_that_always_fails_at_once_is_given_up_after_max_failures():
    async def scenario(rig: Rig) -> None:
        await rig.until(lambda: rig.state("doomed")["state"] == "given_up")
        await asyncio.sleep(0.3)  # nothing more comes
        facts = rig.of("doomed")
        assert [(f["action"], f["outcome"]) for f in facts] == [
            ("start", "failed"), ("respawn", "failed"), ("respawn", "failed"), ("gave_up", "failed")]
        assert all(f["exit_code"] == 1 for f in facts[:3]) and facts[3]["source"] == "supervisor"
        assert "starting it again in 0.05 s (respawn 1 of 2 within 1 min)" in facts[0]["message"]
        assert "starting it again in 0.10 s (respawn 2 of 2 within 1 min)" in facts[1]["message"]
        assert "that is 3 times within 1 min" in facts[2]["message"]
        assert "ended 3 times within 1 min" in facts[3]["message"]
        assert ("doomed", "stderr", "no luck") in rig.lines
        again = await rig.supervisor.start(ROBOT, "doomed", source="api")  # by request it tries again
        assert again["outcome"] == "failed" and rig.state("doomed")["state"] == "backing_off"
        stopped = await rig.supervisor.stop(ROBOT, "doomed", source="api")
        assert stopped["outcome"] == "succeeded" and rig.state("doomed")["state"] == "stopped"

    run(scenario, shell("doomed", "echo 'no luck' >&2; exit 1", respawn_delay=0.05, max_failures=3,
                        failure_window=60))


@pytest.mark.parametrize("options, says", [
    ({"command": "/nonexistent/lidar_driver"}, "the executable /nonexistent/lidar_driver does not exist"),
    ({"command": "no-such-lidar-driver"}, "no executable named no-such-lidar-driver was found on PATH"),
    ({"command": "/bin/sh", "cwd": "/nonexistent/dir"}, "its working directory /nonexistent/dir does not exist"),
    ({"command": "not-executable"}, "is not executable"),
])
def test_a_start_that_cannot_run_fails_and_says_why(tmp_path, options, says):
    if options["command"] == "not-executable":
        (tmp_path / "plain.txt").write_text("echo hi\n")
        options = {"command": str(tmp_path / "plain.txt")}

    async def scenario(rig: Rig) -> None:
        fact = rig.of("lidar")[0]
        assert fact["action"] == "start" and fact["outcome"] == "failed" and fact["pid"] is None
        assert fact["message"].startswith("lidar on agv-1 did not start: ") and says in fact["message"]
        assert fact["message"].endswith("respawn is off.") and rig.state("lidar")["state"] == "exited"

    run(scenario, LaunchProfile(ROBOT, "lidar", respawn=False, **options))


def test_start_of_a_running_process_and_stop_of_a_stopped_one_are_rejected():
    async def scenario(rig: Rig) -> None:
        pid = rig.state("idle")["pid"]
        fact = await rig.supervisor.start(ROBOT, "idle", source="api", user_id=3)
        assert fact["outcome"] == "rejected" and "already running" in fact["message"] and fact["user_id"] == 3
        assert rig.state("idle")["pid"] == pid
        await rig.supervisor.stop(ROBOT, "idle", source="api")
        fact = await rig.supervisor.stop(ROBOT, "idle", source="api")
        assert fact["outcome"] == "rejected" and fact["message"] == "idle on agv-1 is not running."
        fact = await rig.supervisor.start(ROBOT, "idle", source="api", user_id=3)
        assert fact["outcome"] == "succeeded" and fact["source"] == "api" and rig.state("idle")["pid"] == fact["pid"]

    run(scenario, python("idle", SLEEPER))


def test_restart_reports_one_fact_with_the_old_and_the_new_pid():
    async def scenario(rig: Rig) -> None:
        old = rig.state("worker")["pid"]
        before = len(rig.facts)
        fact = await rig.supervisor.restart(ROBOT, "worker", source="api", vouching={"grant": "g"})
        assert rig.facts[before:] == [fact]
        assert fact["action"] == "restart" and fact["outcome"] == "succeeded" and fact["grant"] == "g"
        assert fact["old_pid"] == old and fact["pid"] not in (None, old) and not alive(old)
        row = rig.state("worker")
        assert row["pid"] == fact["pid"] and row["state"] == "running" and row["restarts"] == 1
        await rig.supervisor.stop(ROBOT, "worker", source="api")
        fact = await rig.supervisor.restart(ROBOT, "worker", source="api")  # of a stopped one: a start
        assert fact["outcome"] == "succeeded" and fact["old_pid"] is None and rig.state("worker")["pid"] == fact["pid"]

    run(scenario, python("worker", SLEEPER))


def test_on_launch_is_called_as_each_process_starts_before_it_counts_as_started():
    """(The gateway's discovery then looks for its nodes often: they may appear before EARLY_EXIT_S.)"""
    async def main() -> None:
        launched: list[tuple[str, int]] = []
        rig = Rig()
        rig.supervisor = Supervisor(rig.report, rig.output, on_launch=lambda: launched.append(
            (rig.state("worker")["state"], len(rig.facts))))
        try:
            await rig.supervisor.apply([python("worker", SLEEPER)])
            await rig.supervisor.restart(ROBOT, "worker", source="api")
            # each time before its own fact: the first start's, the restart's (one fact, the start's, before it)
            assert launched == [("starting", 0), ("starting", 1)] and len(rig.facts) == 2
        finally:
            await rig.supervisor.close()
    asyncio.run(main())


def test_apply_starts_the_new_stops_the_removed_and_restarts_the_changed():
    keep, change, drop = python("keep", SLEEPER), python("change", SLEEPER), python("drop", SLEEPER)

    async def scenario(rig: Rig) -> None:
        pids = {row["name"]: row["pid"] for row in rig.supervisor.status()}
        assert set(pids) == {"keep", "change", "drop"} and all(pids.values())
        changed, new = python("change", SLEEPER, stop_grace=2.0), python("new", SLEEPER)
        before = len(rig.facts)
        await rig.supervisor.apply([keep, changed, new])
        made = sorted((f["process"], f["action"], f["outcome"], f["source"]) for f in rig.facts[before:])
        assert made == [("change", "restart", "succeeded", "config"), ("drop", "stop", "succeeded", "config"),
                        ("new", "start", "succeeded", "config")]
        rows = {row["name"]: row for row in rig.supervisor.status()}
        assert set(rows) == {"keep", "change", "new"} and rows["keep"]["pid"] == pids["keep"]
        assert rows["change"]["pid"] != pids["change"] and not alive(pids["drop"]) and not alive(pids["change"])
        before = len(rig.facts)
        await rig.supervisor.apply([keep, changed, new])  # the same again: nothing to do
        assert len(rig.facts) == before
        with pytest.raises(UnknownProcess):
            await rig.supervisor.start(ROBOT, "drop", source="api")

    run(scenario, keep, change, drop)


def test_close_leaves_no_process_running_and_reports_nothing():
    async def scenario(rig: Rig) -> None:
        await rig.until(lambda: rig.lines)
        pids = list(rig.supervisor.pids())
        assert len(pids) == 2
        before = len(rig.facts)
        await rig.supervisor.close()
        assert not [pid for pid in pids if alive(pid)] and len(rig.facts) == before
        assert rig.supervisor.pids() == {}

    run(scenario, python("plain", SLEEPER), python("stubborn", IGNORES_TERM, stop_grace=0.3))


def test_a_stop_ends_the_children_the_process_started_too():
    code = ("import subprocess, sys, time\n"
            f"child = subprocess.Popen([sys.executable, '-c', {IGNORES_TERM!r}])\n"
            "print('child', child.pid, flush=True)\ntime.sleep(30)")

    async def scenario(rig: Rig) -> None:
        await rig.until(lambda: ("parent", "stdout", "ready") in rig.lines)
        child = next(int(line.split()[1]) for _, _, line in rig.lines if line.startswith("child "))
        assert alive(child)
        fact = await rig.supervisor.stop(ROBOT, "parent", source="api")
        assert fact["exit_signal"] == "SIGTERM" and "SIGKILL" not in fact["message"]  # the parent ended on SIGTERM
        await rig.until(lambda: not alive(child), timeout=2.0)  # its child ignored it, and was killed

    run(scenario, python("parent", code))


def test_an_exit_is_seen_at_once_though_a_child_left_behind_holds_the_pipes():
    code = ("import subprocess, sys, time\n"
            "child = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(30)'])\n"
            "print('child', child.pid, flush=True)\ntime.sleep(0.6)\nsys.exit(3)")

    async def scenario(rig: Rig) -> None:
        await rig.until(lambda: rig.of("leaver", "exited"), timeout=2.0)
        child = next(int(line.split()[1]) for _, _, line in rig.lines if line.startswith("child "))
        exited = rig.of("leaver", "exited")[0]
        assert exited["exit_code"] == 3 and exited["message"].endswith("s; respawn is off.")
        await rig.until(lambda: not alive(child), timeout=2.0)  # what it left in its group went with it
        assert rig.state("leaver")["state"] == "exited"

    run(scenario, python("leaver", code, respawn=False))


def test_actions_on_one_process_take_turns():
    async def scenario(rig: Rig) -> None:
        first = rig.state("busy")["pid"]
        one, two, stopped = await asyncio.gather(*(
            action(ROBOT, "busy", source="api")
            for action in (rig.supervisor.restart, rig.supervisor.restart, rig.supervisor.stop)))
        assert one["old_pid"] == first and two["old_pid"] == one["pid"] and stopped["old_pid"] == two["pid"]
        assert [f["action"] for f in rig.of("busy")] == ["start", "restart", "restart", "stop"]
        assert rig.state("busy")["state"] == "stopped" and not any(alive(f["pid"]) for f in (one, two))

    run(scenario, python("busy", SLEEPER, stop_grace=1.0))


def test_a_very_long_line_is_cut_and_the_next_lines_still_come():
    code = ("import sys\nsys.stdout.write('x' * 100000 + '\\nafter\\n' + 'y' * 5000)\nsys.stdout.flush()\n"
            "sys.stderr.write('z' * 4096 + '\\nfine\\n')\nimport time\ntime.sleep(30)")

    async def scenario(rig: Rig) -> None:
        await rig.until(lambda: len(rig.lines) == 5)
        out = [line for _, stream, line in rig.lines if stream == "stdout"]
        assert out == ["x" * LINE_LIMIT + "…", "after", "y" * LINE_LIMIT + "…"]  # the last, too long, not ended yet
        assert [line for _, stream, line in rig.lines if stream == "stderr"] == ["z" * LINE_LIMIT, "fine"]
        await rig.supervisor.stop(ROBOT, "chatty", source="api")
        assert len(rig.lines) == 5  # the rest of the last line dropped

    run(scenario, python("chatty", code))


def test_an_unknown_process_is_refused():
    async def scenario(rig: Rig) -> None:
        for action in (rig.supervisor.start, rig.supervisor.stop, rig.supervisor.restart):
            with pytest.raises(UnknownProcess, match="'ghost'.*'agv-1'"):
                await action(ROBOT, "ghost", source="api")
        with pytest.raises(LookupError):
            await rig.supervisor.start("agv-2", "idle", source="api")

    run(scenario, python("idle", SLEEPER))


def test_the_gateways_own_settings_and_credentials_stay_out_of_its_processes(monkeypatch):
    monkeypatch.setenv("REDIS_URL", "redis://gw-local:s3cret@127.0.0.1:6479/0")
    monkeypatch.setenv("LIFECYCLE_GATEWAY_NAME", "local")
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    names = "('REDIS_URL', 'LIFECYCLE_GATEWAY_NAME', 'ROS_AUTOMATIC_DISCOVERY_RANGE', 'OWN')"
    code = f"import os\nprint(sorted(k for k in {names} if k in os.environ))\nimport time\ntime.sleep(30)"

    async def scenario(rig: Rig) -> None:
        await rig.until(lambda: rig.lines)
        assert rig.lines[0] == ("env", "stdout", "['OWN', 'ROS_AUTOMATIC_DISCOVERY_RANGE']")

    run(scenario, python("env", code, env=(("OWN", "1"),)))
