"""The liveness probe's rhythm (ros_gateway/liveness.py): a process of another host is asked
every pass (a lost link shows only so); one of this host every LOCAL_EVERY passes (its end is
seen in /proc; a probe can only find a hang there), and every pass again once it is silent."""
from __future__ import annotations

import asyncio
from types import SimpleNamespace

from ros_gateway import liveness as lv
from ros_gateway.lifecycle import NodeUnreachable
from ros_gateway.registry import NodeRegistry, RobotInfo, StateChanges

HERE, THERE = b"this-host-p!", b"other-host-p"


def test_processes_of_this_host_are_probed_every_few_passes_others_every_pass(monkeypatch):
    registry = NodeRegistry(StateChanges())
    robot = RobotInfo(1, "agv", 5, "", True)
    for name, participant in (("/local_node", HERE), ("/remote_node", THERE)):
        node = registry.appeared(5, robot, name, frozenset({participant}))
        registry.set_state(node, 3, read=True)  # active, heard from
    liveness = lv.Liveness(registry, {5: SimpleNamespace(domain_id=5)}, interval=1.0, timeout=0.01,
                           local=lambda domain_id, participant: (domain_id, participant) == (5, HERE))
    probed: list[str] = []
    silent = {"now": False}

    async def read_state(domain, name, timeout):
        probed.append(name)
        if silent["now"] and name == "/local_node":
            raise NodeUnreachable("no answer (a callback that never returns)")
        return 3

    monkeypatch.setattr(lv, "read_state", read_state)

    async def passes(count: int) -> None:
        for _ in range(count):
            await liveness.probe()
            await asyncio.sleep(0.01)  # the probes it started

    asyncio.run(passes(2 * lv.LOCAL_EVERY))
    assert probed.count("/remote_node") == 2 * lv.LOCAL_EVERY
    assert probed.count("/local_node") == 2

    # A hang: found at the next probe of the process; from then on it is asked every pass.
    silent["now"] = True
    probed.clear()
    asyncio.run(passes(lv.LOCAL_EVERY))
    assert (5, HERE) in liveness.unreachable
    assert not registry.nodes[(5, "/local_node")].alive
    probed.clear()
    asyncio.run(passes(2))
    assert probed.count("/local_node") == 2 * liveness.misses  # every pass, each with its retries


def test_a_stopped_process_of_this_host_is_told_from_a_running_one():
    """A frozen local process (SIGSTOP) is probed at every pass, as a remote one: the gateway's
    ``local`` answer leaves it out (ros_gateway/service.py) once /proc shows it stopped."""
    import signal
    import subprocess

    from ros_gateway.processes import LocalProcesses, OsProcess
    from tests import stack

    child = subprocess.Popen(["sleep", "30"])
    try:
        processes, process = LocalProcesses(), OsProcess(child.pid, "")
        assert not processes.stopped(process)
        child.send_signal(signal.SIGSTOP)
        stack.wait_for(lambda: processes.stopped(process), 5, "the process to show stopped")
        child.send_signal(signal.SIGCONT)
        stack.wait_for(lambda: not processes.stopped(process), 5, "the process to run again")
    finally:
        child.kill()
        child.wait(5)
    assert not processes.stopped(process)  # gone: not stopped either

