"""Containers and systemd units running a robot's nodes (ros_gateway/host_units.py): which one a
process is in, read from the kernel's own /proc data (a cgroup this test makes), and what the
gateway does and reports when asked to restart, stop or start one. (The Docker Engine's part runs
against the real engine in tests/deploy/test_host_units.py; systemd, which does not run this
machine, is played by a small systemctl script that keeps its unit's state in a file.)"""
from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from ros_gateway.host_units import DockerEngine, HostUnit, HostUnits, Systemd, UnitError, cgroup_path, unit_in
from ros_gateway.shared import protocol

CONTAINER = "ecc652cbdbbbcaa148721cd45c5789ba8e2a82c9d674ef3d3801f130496087f0"


@pytest.mark.parametrize(("text", "expected"), [
    (f"0::/system.slice/docker-{CONTAINER}.scope\n", ("docker", CONTAINER)),  # v2, systemd's cgroup driver
    (f"9:name=systemd:/docker/{CONTAINER}\n1:cpu:/docker/{CONTAINER}\n0::/docker/{CONTAINER}\n",
     ("docker", CONTAINER)),  # v1 / hybrid, cgroupfs driver
    ("0::/system.slice/agv-drivers.service\n", ("systemd", "agv-drivers.service")),
    # A systemd in a container on a hybrid host: only its own hierarchy has the unit.
    (f"9:name=systemd:/docker/{CONTAINER}/system.slice/demo.service\n8:pids:/docker/{CONTAINER}\n"
     f"0::/docker/{CONTAINER}\n", ("docker", CONTAINER)),
    ("12:name=systemd:/system.slice/agv-drivers.service/control\n", ("systemd", "agv-drivers.service")),
    ("0::/user.slice/user-1000.slice/user@1000.service/app.slice/x.service\n", None),  # a user's manager's
    ("0::/user.slice/user-1000.slice/session-3.scope\n", None),  # a login shell
    ("0::/\n", None),
    ("", None),
])
def test_a_cgroup_names_its_container_or_unit(text, expected):
    assert unit_in(cgroup_path(text)) == expected


def test_inside_its_own_container_the_gateway_looks_for_systemd_units_only():
    node = f"/docker/{CONTAINER}/system.slice/demo-node.service"
    assert unit_in(node) == ("docker", CONTAINER)  # seen from the host: the container
    own = f"/docker/{CONTAINER}/system.slice/lifecycle-gateway.service"
    assert unit_in(node, own) == ("systemd", "demo-node.service")  # the gateway's neighbour under the same systemd


@pytest.fixture
def unit_cgroup():
    """A process in a cgroup named like a systemd service, made in this kernel (as root), and its pid."""
    v1 = Path("/sys/fs/cgroup/systemd")
    root = v1 if (v1 / "cgroup.procs").exists() else Path("/sys/fs/cgroup")
    group = root / "system.slice" / f"lc-test-{os.getpid()}.service"
    group.mkdir(parents=True, exist_ok=True)
    child = subprocess.Popen(["sleep", "60"])
    try:
        (group / "cgroup.procs").write_text(str(child.pid))
        yield child.pid, group.name
    finally:
        child.kill()
        child.wait()
        for _ in range(50):  # the kernel empties the group just after the process is reaped
            try:
                group.rmdir()
                break
            except OSError:
                asyncio.run(asyncio.sleep(0.05))


class FakeSystemctl(Systemd):
    """systemctl with a unit's state in a file: stop records a SIGTERM end, start a new pid."""

    def __init__(self, tmp: Path) -> None:
        script = tmp / "systemctl"
        state = tmp / "unit-state"
        state.write_text("LoadState=loaded\nActiveState=active\nMainPID=4100\nExecMainCode=0\nExecMainStatus=0\n"
                         "NRestarts=0\nTimeoutStopUSec=1min 30s\n")
        script.write_text(textwrap.dedent(f"""\
            #!{sys.executable}
            import sys
            path = {str(state)!r}
            state = dict(line.split("=", 1) for line in open(path).read().splitlines())
            verb = sys.argv[1]
            if verb == "show":
                print("\\n".join(f"{{k}}={{v}}" for k, v in state.items()))
            elif verb == "stop":
                state.update(ActiveState="inactive", MainPID="0", ExecMainCode="2", ExecMainStatus="15")
            elif verb == "start":
                state.update(ActiveState="active", MainPID=str(int(state.get("Last", "4100")) + 1))
                state["Last"] = state["MainPID"]
            with open(path, "w") as out:
                out.write("\\n".join(f"{{k}}={{v}}" for k, v in state.items()) + "\\n")
            with open(path + ".calls", "a") as calls:
                calls.write(" ".join(sys.argv[1:]) + "\\n")
        """))
        script.chmod(0o755)
        super().__init__(systemctl=str(script))
        self.calls = Path(f"{state}.calls")

    def available(self) -> bool:
        return True


def test_a_process_in_a_unit_is_attributed_to_it_from_real_proc_data(unit_cgroup, tmp_path):
    pid, unit = unit_cgroup
    units = HostUnits(lambda **f: f, DockerEngine(""), FakeSystemctl(tmp_path))
    found = asyncio.run(units.identify(pid))
    assert found == HostUnit("systemd", unit, f"systemd:{unit}")
    assert protocol.HOST_PROCESS_RE.match(found.name)
    without = HostUnits(lambda **f: f, DockerEngine(""), Systemd(enabled=False))
    assert asyncio.run(without.identify(pid)) is None  # no supervisor to reach: nothing offered
    assert not without.identified(pid)  # ... for now: asked again (systemd or Docker may come up later)
    assert units.identified(pid)
    assert asyncio.run(units.identify(os.getpid())) is None  # this test's own process: no unit


def control(units: HostUnits, action: str, robot: str = "agv-1", name: str = "systemd:agv-drivers.service") -> dict:
    return asyncio.run(units.control(robot, name, action, source="api", user_id=7))


def test_restart_stop_and_start_of_an_attributed_unit_are_reported(tmp_path):
    systemctl = FakeSystemctl(tmp_path)
    launched: list[str] = []  # (the gateway's discovery then looks for the unit's nodes often)
    units = HostUnits(lambda **f: f, DockerEngine(""), systemctl,
                      on_launch=lambda: launched.append(systemctl.calls.read_text().split()[-2]))
    units.attribute("agv-1", HostUnit("systemd", "agv-drivers.service", "systemd:agv-drivers.service"))

    restart = control(units, "restart")
    assert (restart["outcome"], restart["supervisor"], restart["old_pid"], restart["pid"]) == (
        "succeeded", "systemd", 4100, 4101)
    assert (restart["exit_code"], restart["exit_signal"], restart["user_id"]) == (None, "SIGTERM", 7)
    assert restart["message"] == "Unit agv-drivers.service of agv-1 restarted as pid 4101 (pid 4100 ended by SIGTERM)."
    assert "stop agv-drivers.service" in systemctl.calls.read_text()

    stop = control(units, "stop")
    assert (stop["outcome"], stop["old_pid"], stop["pid"], stop["exit_signal"]) == ("succeeded", 4101, None, "SIGTERM")
    again = control(units, "stop")
    assert (again["outcome"], again["message"]) == ("rejected", "Unit agv-drivers.service of agv-1 is not running.")
    start = control(units, "start")
    assert (start["outcome"], start["pid"], start["exit_signal"]) == ("succeeded", 4102, None)
    assert launched == ["start", "start"]  # once the restart's and the start's start had run, not on a stop


def test_only_a_unit_attributed_to_that_robot_is_acted_on(tmp_path):
    systemctl = FakeSystemctl(tmp_path)
    units = HostUnits(lambda **f: f, DockerEngine(""), systemctl)
    units.attribute("agv-1", HostUnit("systemd", "agv-drivers.service", "systemd:agv-drivers.service"))
    for robot, name in (("agv-2", "systemd:agv-drivers.service"), ("agv-1", "systemd:sshd.service"),
                        ("agv-1", "docker:agv-drivers.service")):
        with pytest.raises(LookupError):
            control(units, "restart", robot, name)
    assert not systemctl.calls.exists()  # nothing ran


def test_a_supervisor_that_does_not_answer_gives_a_failed_record_in_words(tmp_path):
    units = HostUnits(lambda **f: f, DockerEngine(str(tmp_path / "no-docker.sock")), Systemd(enabled=False))
    units.attribute("agv-1", HostUnit("docker", CONTAINER, "docker:drivers"))
    fact = control(units, "restart", name="docker:drivers")
    assert fact["outcome"] == "failed"
    assert fact["message"].startswith("Container drivers of agv-1 was not restarted: the Docker Engine at ")
    assert "could not be asked" in fact["message"]


def test_a_unit_stop_time_is_read_in_systemd_words():
    from ros_gateway.host_units import _usec
    assert (_usec("1min 30s"), _usec("90s"), _usec("500ms"), _usec("infinity"), _usec("")) == (
        90.0, 90.0, 0.5, 120.0, 90.0)


def test_a_container_the_engine_could_not_name_is_asked_again_less_and_less_often(tmp_path, monkeypatch):
    """An engine that does not answer (restarting, overloaded) is not the last word on a node's
    container: it is asked again after a back-off, with one warning, and the answer then settles it."""
    proc = tmp_path / "proc"
    (proc / "4100").mkdir(parents=True)
    (proc / "4100" / "cgroup").write_text(f"0::/system.slice/docker-{CONTAINER}.scope\n")
    socket_file = tmp_path / "docker.sock"
    socket_file.write_text("")  # there, but not a socket: every call fails
    units = HostUnits(lambda **f: f, DockerEngine(str(socket_file)), Systemd(enabled=False), proc=proc)
    asked: list[str] = []

    async def inspect(ident: str) -> dict:
        asked.append(ident)
        if len(asked) < 3:
            raise UnitError("no answer within 5 s")
        return {"Name": "/drivers"}

    monkeypatch.setattr(units.docker, "inspect", inspect)
    clock = [1000.0]
    monkeypatch.setattr("ros_gateway.host_units.time.monotonic", lambda: clock[0])
    assert asyncio.run(units.identify(4100)) is None and not units.identified(4100)
    assert asyncio.run(units.identify(4100)) is None and len(asked) == 1  # within the back-off: not asked
    clock[0] += 2.0
    assert asyncio.run(units.identify(4100)) is None and len(asked) == 2
    clock[0] += 2.0
    assert asyncio.run(units.identify(4100)) is None and len(asked) == 2  # the wait doubled
    clock[0] += 2.0
    assert asyncio.run(units.identify(4100)) == HostUnit("docker", CONTAINER, "docker:drivers")
    assert units.identified(4100) and len(asked) == 3
