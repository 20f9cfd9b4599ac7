"""How the gateway ties a DDS participant of its own host to an OS process and sees it end
(ros_gateway/processes.py), with real processes: one that maps a Fast DDS shared-memory port
file of a ROS domain, as a Fast DDS participant does, is found from the low 16 bits of its PID
(as a GUID prefix carries them) and seen ended at once when it is killed, reaped or not."""
from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ros_gateway.process_owners import ProcessOwners
from ros_gateway.processes import DOMAIN_GAIN, FASTDDS_VENDOR, PORT_BASE, LocalProcesses
from ros_gateway.registry import LiveNode, NodeRegistry, RobotInfo, StateChanges

DOMAIN = 231  # no test or robot here uses it: its port files are this test's alone
HOST = b"\x12\x34"
MAPPER = """
import mmap, sys, time
with open(sys.argv[1], "r+b") as f:
    m = mmap.mmap(f.fileno(), 4096)
    print("mapped", flush=True)
    time.sleep(120)
"""


def prefix_of(pid: int, host: bytes = HOST) -> bytes:
    """A Fast DDS GUID prefix as a participant of process ``pid`` on ``host`` has it."""
    return FASTDDS_VENDOR + host + (pid & 0xFFFF).to_bytes(2, "little") + b"\xab\xcd" + b"\x00" * 6


@pytest.fixture
def port_file():
    path = Path(f"/dev/shm/fastrtps_port{PORT_BASE + DOMAIN_GAIN * DOMAIN + 11}")
    path.write_bytes(b"\0" * 4096)
    yield path
    path.unlink(missing_ok=True)


def start_mapper(path: Path) -> subprocess.Popen:
    process = subprocess.Popen([sys.executable, "-c", MAPPER, str(path)], stdout=subprocess.PIPE, text=True)
    assert process.stdout.readline().strip() == "mapped"
    return process


def watcher() -> LocalProcesses:
    processes = LocalProcesses()
    processes.learn_host(FASTDDS_VENDOR + HOST + b"\x00" * 12)
    return processes


@pytest.mark.parametrize("reaped", [True, False], ids=["reaped", "zombie"])
def test_a_participants_process_is_found_and_seen_ended_when_killed(port_file, reaped):
    process = start_mapper(port_file)
    try:
        processes = watcher()
        prefix = prefix_of(process.pid)
        assert processes.process(DOMAIN, prefix).pid == process.pid
        assert not processes.ended(DOMAIN, prefix)
        assert processes.ended_among(DOMAIN, [prefix]) == set()
        # Another domain's participant, or another host's, is not this process.
        assert processes.process(DOMAIN + 1, prefix) is None
        assert processes.process(DOMAIN, prefix_of(process.pid, host=b"\x99\x99")) is None
        os.kill(process.pid, signal.SIGKILL)
        if reaped:
            process.wait(5)
        else:  # its parent has not collected it yet (a supervisor between two polls)
            os.waitid(os.P_PID, process.pid, os.WEXITED | os.WNOWAIT)
        assert processes.ended(DOMAIN, prefix)
        assert processes.all_ended(DOMAIN, frozenset({prefix}))
    finally:
        process.kill()
        process.wait(5)


def test_a_process_that_maps_no_port_of_the_domain_is_not_taken_for_the_participant(port_file):
    other = subprocess.Popen([sys.executable, "-c", "import time; print('up', flush=True); time.sleep(120)"],
                             stdout=subprocess.PIPE, text=True)
    try:
        assert other.stdout.readline().strip() == "up"
        processes = watcher()
        assert processes.process(DOMAIN, prefix_of(other.pid)) is None
        other.kill()
        other.wait(5)
        assert not processes.ended(DOMAIN, prefix_of(other.pid))  # not known: DDS decides
    finally:
        other.kill()
        other.wait(5)


LATE_MAPPER = """
import mmap, sys, time
sys.stdin.readline()  # told to start its participant
with open(sys.argv[1], "r+b") as f:
    m = mmap.mmap(f.fileno(), 4096)
    print("mapped", flush=True)
    time.sleep(120)
"""


@pytest.fixture
def late_mapper(port_file):
    """A process whose participant is not up yet: it maps the domain's port when told to."""
    process = subprocess.Popen([sys.executable, "-c", LATE_MAPPER, str(port_file)], stdin=subprocess.PIPE,
                               stdout=subprocess.PIPE, text=True)

    def map_port() -> None:
        process.stdin.write("go\n")
        process.stdin.flush()
        assert process.stdout.readline().strip() == "mapped"

    yield process, map_port
    process.kill()
    process.wait(5)


def test_a_participant_not_matched_at_first_is_matched_on_a_later_look(late_mapper, monkeypatch):
    monkeypatch.setattr("ros_gateway.processes.RETRY_FIRST_S", 0.2)
    process, map_port = late_mapper
    processes = watcher()
    prefix = prefix_of(process.pid)
    assert processes.process(DOMAIN, prefix) is None  # seen in DDS before /proc shows it as a participant
    assert processes.unmatched(DOMAIN, prefix)
    map_port()
    assert processes.process(DOMAIN, prefix) is None  # not looked for again at once: a back-off
    time.sleep(0.25)
    assert processes.process(DOMAIN, prefix).pid == process.pid
    assert not processes.unmatched(DOMAIN, prefix)
    # Another host's participant is not one to look for here.
    assert not processes.unmatched(DOMAIN, prefix_of(process.pid, host=b"\x99\x99"))


def test_a_nodes_launch_profile_is_found_when_its_process_was_not_matched_at_first_look(late_mapper, monkeypatch):
    """The gateway's first look at a node can come before its process is matched (a robot's
    units starting together at boot): the owner is looked for again, not given up for good."""
    monkeypatch.setattr("ros_gateway.processes.RETRY_FIRST_S", 0.2)
    process, map_port = late_mapper
    registry = NodeRegistry(StateChanges())
    robot = RobotInfo(id=1, name="agv", domain_id=DOMAIN, namespace="")
    node = LiveNode(robot=robot, name="/lidar_driver", alive=True, live=frozenset({prefix_of(process.pid)}))
    registry.nodes[(DOMAIN, node.name)] = node
    reported: list[str] = []
    owners = ProcessOwners(registry, watcher(), lambda: {process.pid: ("agv", "drivers")},
                           lambda n: reported.append(n.process))
    asyncio.run(owners.refresh())
    assert node.process == "" and reported == []
    map_port()
    time.sleep(0.25)
    asyncio.run(owners.refresh())
    assert node.process == "drivers" and reported == ["drivers"]
    asyncio.run(owners.refresh())  # settled: not reported again
    assert reported == ["drivers"]
