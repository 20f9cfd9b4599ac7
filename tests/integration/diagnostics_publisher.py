"""A robot's diagnostics for tests and benchmarks: a real rclpy node publishing DiagnosticArray on
its namespace's ``diagnostics`` (or ``diagnostics_agg``) at a rate, steered through stdin.

    python tests/integration/diagnostics_publisher.py DOMAIN --namespace /r1 --statuses 100 --rate 1

Statuses are named "<node>: check N" (diagnostic_updater's way) unless set by name; with --churn
a key/value "seq" of each changes with every message. Each stdin line
is a JSON object: {"name": N, "level": 0-3, "message": M, "values": [[k, v]]} sets (or adds) a status,
{"drop": N} stops publishing it, {"rate": HZ} changes the rate. After each line it prints one JSON
line {"published": N, "at": <wall time of the first message that carried it>} for a set or drop.
Prints "ready" once publishing.
"""
from __future__ import annotations

import argparse
import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve()


class Source:
    """The publisher in a process of its own, steered from a test or a benchmark."""

    def __init__(self, domain: int, env: dict[str, str], *args: str) -> None:
        self.popen = subprocess.Popen([sys.executable, str(HERE), str(domain), *args], env=env, text=True,
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, start_new_session=True)
        self.lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()
        assert self.lines.get(timeout=30) == "ready"

    def _read(self) -> None:
        for line in self.popen.stdout:
            self.lines.put(line.strip())

    def send(self, **order) -> float:
        """Give an order; for a set or drop, the wall time of the first message that carried it."""
        self.popen.stdin.write(json.dumps(order) + "\n")
        self.popen.stdin.flush()
        if "rate" in order:
            return time.time()
        return json.loads(self.lines.get(timeout=10))["at"]

    def stop(self) -> None:
        if self.popen.poll() is None:
            try:
                self.popen.stdin.close()  # its end: it leaves DDS as a node does
                self.popen.wait(5)
                return
            except (OSError, subprocess.TimeoutExpired):
                pass
            os.killpg(self.popen.pid, signal.SIGTERM)
            try:
                self.popen.wait(5)
            except subprocess.TimeoutExpired:
                os.killpg(self.popen.pid, signal.SIGKILL)
                self.popen.wait(5)


def main() -> int:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    parser = argparse.ArgumentParser()
    parser.add_argument("domain", type=int)
    parser.add_argument("--namespace", default="")
    parser.add_argument("--node", default="diag_source")
    parser.add_argument("--topic", default="diagnostics")
    parser.add_argument("--statuses", type=int, default=3)
    parser.add_argument("--rate", type=float, default=1.0)
    parser.add_argument("--churn", action="store_true",
                        help="a key/value of every status changes with each message (a measured frequency does)")
    args = parser.parse_args()
    context = rclpy.context.Context()
    rclpy.init(context=context, domain_id=args.domain)
    node = rclpy.create_node(args.node, namespace=args.namespace or None, context=context)
    publisher = node.create_publisher(DiagnosticArray, args.topic, 10)
    lock = threading.Lock()
    statuses: dict[str, DiagnosticStatus] = {}
    for index in range(args.statuses):
        name = f"{args.node}: check {index}"
        statuses[name] = DiagnosticStatus(level=DiagnosticStatus.OK, name=name, message="fine",
                                          hardware_id=f"hw{index}", values=[KeyValue(key="index", value=str(index))])
    announce: list[str] = []  # names whose next publication is reported
    rate = [args.rate]
    sequence = [0]
    stop = threading.Event()

    def publish_loop() -> None:
        while not stop.is_set():
            began = time.monotonic()
            with lock:
                sequence[0] += 1
                if args.churn:
                    for status in statuses.values():
                        status.values = [v for v in status.values if v.key != "seq"] + [
                            KeyValue(key="seq", value=str(sequence[0]))]
                message = DiagnosticArray(status=list(statuses.values()))
                message.header.stamp = node.get_clock().now().to_msg()
                reported, announce[:] = list(announce), []
            publisher.publish(message)
            at = time.time()
            for name in reported:
                print(json.dumps({"published": name, "at": at}), flush=True)
            stop.wait(max(0.0, 1.0 / rate[0] - (time.monotonic() - began)))

    thread = threading.Thread(target=publish_loop, daemon=True)
    thread.start()
    print("ready", flush=True)
    try:
        for line in sys.stdin:
            order = json.loads(line)
            with lock:
                if "rate" in order:
                    rate[0] = float(order["rate"])
                elif "drop" in order:
                    statuses.pop(order["drop"], None)
                    announce.append(order["drop"])
                else:
                    name = order["name"]
                    statuses[name] = DiagnosticStatus(
                        level=bytes([int(order.get("level", 0))]), name=name, message=order.get("message", ""),
                        hardware_id=order.get("hardware_id", ""),
                        values=[KeyValue(key=k, value=v) for k, v in order.get("values", [])])
                    announce.append(name)
    except (KeyboardInterrupt, BrokenPipeError):
        pass
    stop.set()
    thread.join(timeout=2)
    context.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
