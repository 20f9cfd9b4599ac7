"""What a killed gateway's launch profiles left running (ros_gateway/leftovers.py): found by the mark
in their environment, only that gateway's, and ended (SIGTERM, then SIGKILL for one that ignores it)."""
from __future__ import annotations

import asyncio
import os
import subprocess
import sys

from ros_gateway import leftovers


def marked(value: str, ignore_term: bool = False) -> subprocess.Popen:
    code = "import signal, time\n" + ("signal.signal(signal.SIGTERM, signal.SIG_IGN)\n" if ignore_term else "") + \
        "print('ready', flush=True)\ntime.sleep(60)"
    child = subprocess.Popen([sys.executable, "-c", code], env={**os.environ, leftovers.MARK: value},
                             stdout=subprocess.PIPE)
    assert child.stdout.readline() == b"ready\n"
    return child


def test_only_the_gateways_own_leftovers_are_found_and_ended(monkeypatch):
    monkeypatch.setattr(leftovers, "GRACE_S", 0.5)
    ours = marked(leftovers.mark("cell-x", "agv-1", "drivers"))
    stubborn = marked(leftovers.mark("cell-x", "agv-1", "planner"), ignore_term=True)
    other = marked(leftovers.mark("cell-xy", "agv-1", "drivers"))  # another gateway's (a longer name)
    try:
        found = leftovers.find("cell-x")
        assert other.pid not in found
        assert found == {ours.pid: "cell-x/agv-1/drivers", stubborn.pid: "cell-x/agv-1/planner"}
        ended = asyncio.run(leftovers.end("cell-x"))
        assert ended == {"cell-x/agv-1/drivers": [ours.pid], "cell-x/agv-1/planner": [stubborn.pid]}
        assert ours.wait(5) == -15 and stubborn.wait(5) == -9  # SIGTERM; SIGKILL after the grace
        assert other.poll() is None
    finally:
        for child in (ours, stubborn, other):
            child.kill()
            child.wait()


def test_the_same_gateway_name_of_another_site_is_another_owner():
    demo = leftovers.owner("local", "redis://127.0.0.1:6479/0", "lifecycle")
    tests = leftovers.owner("local", "redis://127.0.0.1:41234/0", "lifecycle-test")
    assert demo.startswith("local@") and demo != tests
    assert demo == leftovers.owner("local", "redis://:s3cret@127.0.0.1:6479/0", "lifecycle")  # not the password
