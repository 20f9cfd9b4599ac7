"""CPU and memory of a robot's processes (ros_gateway/process_usage.py), from this kernel's /proc:
a busy process group and an idle one told apart, a restarted process measured afresh."""
from __future__ import annotations

import asyncio
import subprocess
import sys

from ros_gateway.process_usage import ProcessUsage

BUSY = "import time\nend = time.time() + 30\nwhile time.time() < end: pass"
IDLE = "import subprocess, sys, time\nsubprocess.Popen([sys.executable, '-c', 'import time; time.sleep(30)'])\n" \
       "time.sleep(30)"


def group(code: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", code], start_new_session=True)


def test_a_busy_group_and_an_idle_one_with_its_child():
    busy, idle = group(BUSY), group(IDLE)
    try:
        asyncio.run(asyncio.sleep(0.5))  # the idle one's child started
        usage = asyncio.run(ProcessUsage().measure({"busy": busy.pid, "idle": idle.pid}, {}))
        assert usage["busy"]["cpu_percent"] > 50 and usage["busy"]["processes"] == 1
        assert usage["idle"]["cpu_percent"] < 10 and usage["idle"]["processes"] == 2  # with its child
        assert all(1 << 20 < u["rss_bytes"] < 1 << 30 for u in usage.values())
    finally:
        for child in (busy, idle):
            subprocess.run(["pkill", "-KILL", "-g", str(child.pid)], check=False)
            child.wait()


def test_a_restarted_process_is_measured_afresh_not_against_its_predecessor():
    meter, first = ProcessUsage(), group(BUSY)
    try:
        assert asyncio.run(meter.measure({"drivers": first.pid}, {}))["drivers"]["cpu_percent"] > 50
        asyncio.run(asyncio.sleep(0.5))
    finally:
        first.kill()
        first.wait()
    second = group(BUSY)
    try:
        again = asyncio.run(meter.measure({"drivers": second.pid}, {}))["drivers"]
        assert again["cpu_percent"] is not None and again["cpu_percent"] > 50
    finally:
        second.kill()
        second.wait()
    gone = asyncio.run(meter.measure({"drivers": second.pid}, {}))["drivers"]
    assert gone["processes"] == 0 and gone["rss_bytes"] == 0
