"""A warm rclpy process of the benchmark's own, driven by JSON lines on stdin.

It is the floor the gateway is compared with (a direct ChangeState call from a process
whose client has already found the service) and the trigger of the push-latency scenario
(it timestamps each ~/transition_event it receives with the machine's monotonic clock,
which every process on the machine shares).

    python -m tests.benchmarks.ros_probe DOMAIN
    -> {"op": "change", "node": "/n_000", "transition": 1}   <- {"ok": true, "ms": 0.9, "sent": T}
       (with "check": true it first reads the state, as the gateway does before every change)
    -> {"op": "state", "node": "/n_000"}                     <- {"ok": true, "label": "inactive"}
    -> {"op": "watch", "node": "/n_000"}                     <- {"ok": true}
    -> {"op": "events"}                                      <- {"events": [[T, "unconfigured", "configuring"]]}
"""
from __future__ import annotations

import json
import os
import sys
import threading
import time
from typing import Any

import rclpy
from lifecycle_msgs.msg import TransitionEvent
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.context import Context
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor


class Probe:
    def __init__(self, domain: int) -> None:
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node(f"bench_probe_{os.getpid()}", context=self.context,
                                      start_parameter_services=False)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.clients: dict[str, Any] = {}
        self.subscriptions: dict[str, Any] = {}
        self.events: list[tuple[float, str, str]] = []
        self.lock = threading.Lock()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except ExternalShutdownException:
            pass

    def client(self, fqn: str, service: str, srv_type: Any, timeout: float) -> Any:
        client = self.clients.get(f"{fqn}/{service}")
        if client is None:
            client = self.clients[f"{fqn}/{service}"] = self.node.create_client(srv_type, f"{fqn}/{service}")
        if not client.wait_for_service(timeout_sec=timeout):
            raise TimeoutError(f"{fqn}/{service} not available within {timeout} s")
        return client

    @staticmethod
    def _call(client: Any, request: Any, timeout: float) -> Any:
        done = threading.Event()
        future = client.call_async(request)
        future.add_done_callback(lambda _f: done.set())
        if not done.wait(timeout):
            client.remove_pending_request(future)
            raise TimeoutError(f"{client.srv_name} did not answer within {timeout} s")
        return future.result()

    def change(self, node: str, transition: int, check: bool = False, timeout: float = 10.0) -> dict:
        change = self.client(node, "change_state", ChangeState, timeout)
        get = self.client(node, "get_state", GetState, timeout) if check else None
        request = ChangeState.Request()
        request.transition.id = transition
        sent = time.monotonic()
        began = time.perf_counter()
        if get is not None:
            self._call(get, GetState.Request(), timeout)
        response = self._call(change, request, timeout)
        return {"ok": bool(response.success), "ms": (time.perf_counter() - began) * 1000, "sent": sent}

    def state(self, node: str, timeout: float = 10.0) -> dict:
        response = self._call(self.client(node, "get_state", GetState, timeout), GetState.Request(), timeout)
        return {"ok": True, "label": response.current_state.label}

    def watch(self, node: str) -> dict:
        if node not in self.subscriptions:
            self.subscriptions[node] = self.node.create_subscription(
                TransitionEvent, f"{node}/transition_event", self._on_event, 10
            )
        return {"ok": True}

    def _on_event(self, msg: TransitionEvent) -> None:
        received = time.monotonic()
        with self.lock:
            self.events.append((received, msg.start_state.label, msg.goal_state.label))

    def take_events(self) -> dict:
        with self.lock:
            events, self.events = self.events, []
        return {"events": events}

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.context.try_shutdown()


def main(domain: int) -> int:
    probe = Probe(domain)
    print(json.dumps({"ready": True}), flush=True)
    handlers = {"change": probe.change, "state": probe.state, "watch": probe.watch,
                "events": lambda: probe.take_events()}
    for line in sys.stdin:
        command = json.loads(line)
        op = command.pop("op")
        if op == "quit":
            break
        try:
            answer = handlers[op](**command)
        except Exception as exc:  # the harness reads the error and fails the scenario
            answer = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
        print(json.dumps(answer), flush=True)
    probe.close()
    return 0


if __name__ == "__main__":
    sys.exit(main(int(sys.argv[1])))
