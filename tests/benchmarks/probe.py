"""The harness's handle on a line-protocol helper process (ros_probe.py, flooder.py):
send one JSON command, read one JSON answer, every wait bounded."""
from __future__ import annotations

import json
import select
import subprocess
import time
from typing import Any

from tests.benchmarks.harness import Stack
from tests.benchmarks.processes import PYTHON, BenchError, Child


class LineProcess:
    def __init__(self, stack: Stack, name: str, module: str, *args: str, ready_timeout: float = 60.0) -> None:
        self.child = stack.spawn(name, [PYTHON, "-m", module, *args], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        self.read(ready_timeout)  # the "ready" line

    @property
    def pid(self) -> int:
        return self.child.pid

    def read(self, timeout: float) -> dict[str, Any]:
        stdout = self.child.popen.stdout
        assert stdout is not None
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            readable, _, _ = select.select([stdout], [], [], max(remaining, 0))
            if readable:
                line = stdout.readline()
                if not line:
                    raise BenchError(f"{self.child.name} exited:\n{self.child.output()[-2000:]}")
                return json.loads(line)
            if remaining <= 0:
                raise BenchError(f"{self.child.name} did not answer within {timeout:g} s")

    def call(self, op: str, timeout: float = 30.0, **arguments: Any) -> dict[str, Any]:
        stdin = self.child.popen.stdin
        assert stdin is not None
        stdin.write((json.dumps({"op": op, **arguments}) + "\n").encode())
        stdin.flush()
        return self.read(timeout)

    def close(self) -> None:
        try:
            self.call("quit", timeout=0.1)
        except (BenchError, OSError, ValueError):
            pass
        self.child.stop()


class RosProbe(LineProcess):
    """A warm rclpy client in ``domain`` (see ros_probe.py)."""

    def __init__(self, stack: Stack, domain: int) -> None:
        super().__init__(stack, f"probe-{domain}", "tests.benchmarks.ros_probe", str(domain))
        self.changes = 0  # transitions made (each one the gateway sees as external)

    def change(self, fqn: str, transition_id: int, check: bool = False) -> dict[str, Any]:
        answer = self.call("change", node=fqn, transition=transition_id, check=check)
        if not answer.get("ok"):
            raise BenchError(f"direct ChangeState {transition_id} on {fqn} failed: {answer}")
        self.changes += 1
        return answer


__all__ = ["Child", "LineProcess", "RosProbe"]
