"""Which nodes the gateway counts as running lifecycle nodes (RosDomain.lifecycle_node_names),
on real rclpy. The node list of rmw_fastrtps can stay behind the endpoints (one
ros_discovery_info message per process: a process that made 50 nodes at once on a loaded
machine was listed with 21 of them for minutes); a node that publishes its transition events
is running whatever the list says, and one that stopped publishing them is not."""
from __future__ import annotations

import asyncio
import gc
import threading
import time

import pytest
import rclpy
from lifecycle_msgs.srv import GetState
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import LifecycleNode

from ros_gateway import domain as domain_module
from ros_gateway.domain import RosDomain
from tests import stack

DOMAIN_OFFSET = 2
FOUND_WITHIN_S = 10.0


class Process:
    """A lifecycle node in a context (a DDS participant) of its own, like a robot's process."""

    def __init__(self, domain_id: int, name: str) -> None:
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node: LifecycleNode | None = LifecycleNode(name, context=self.context)
        self.executor: SingleThreadedExecutor | None = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.running = True

    def spin(self) -> Process:
        """Answer its services (in a thread of its own, until end())."""
        threading.Thread(target=self.executor.spin, daemon=True).start()
        return self

    def end(self) -> None:
        """Like the process exiting: every endpoint of the node leaves. destroy_node alone
        does not take the transition_event publisher: rclpy's lifecycle state machine keeps it
        until the node object is collected."""
        if self.running:
            self.running = False
            self.executor.shutdown(timeout_sec=1.0)
            self.node.destroy_node()
            self.node = self.executor = None
            gc.collect()
            rclpy.shutdown(context=self.context)


@pytest.fixture
def graph(gateway_environ):
    domain_id = stack.domain(DOMAIN_OFFSET)
    processes = {name: Process(domain_id, name) for name in ("listed_node", "unlisted_node")}
    loop = asyncio.new_event_loop()
    ros = RosDomain(domain_id, loop, on_transition_event=lambda *a: None, on_log=lambda *a: None)
    ros.start()
    try:
        yield ros, processes
    finally:
        ros.stop()
        loop.close()
        for process in processes.values():
            process.end()


def hide_from_node_list(ros: RosDomain, monkeypatch, fqn: str) -> None:
    """What rmw_fastrtps does when a process's ros_discovery_info update is missed: the node's
    endpoints are known, the node list lacks it."""
    real = ros.node.get_node_names_and_namespaces
    monkeypatch.setattr(ros.node, "get_node_names_and_namespaces",
                        lambda: [(n, ns) for n, ns in real() if f"{ns.rstrip('/')}/{n}" != fqn])


def names_within(ros: RosDomain, wanted: set[str], timeout: float, known=()) -> set[str]:
    deadline = time.monotonic() + timeout
    while (found := ros.lifecycle_node_names(known)) != wanted and time.monotonic() < deadline:
        time.sleep(0.2)
    return found


def test_a_lifecycle_node_missing_from_the_node_list_is_found_by_its_transition_events(graph, monkeypatch):
    ros, _processes = graph
    hide_from_node_list(ros, monkeypatch, "/unlisted_node")
    assert names_within(ros, {"/listed_node", "/unlisted_node"}, FOUND_WITHIN_S) == {"/listed_node", "/unlisted_node"}


def test_an_unlisted_node_that_stops_publishing_is_gone(graph, monkeypatch):
    ros, processes = graph
    hide_from_node_list(ros, monkeypatch, "/unlisted_node")
    assert names_within(ros, {"/listed_node", "/unlisted_node"}, FOUND_WITHIN_S) == {"/listed_node", "/unlisted_node"}
    # Our own clients keep /unlisted_node/get_state in the graph; that alone is no proof of life.
    ros.node.create_client(GetState, "/unlisted_node/get_state")
    processes["unlisted_node"].end()
    assert names_within(ros, {"/listed_node"}, FOUND_WITHIN_S, known=["/unlisted_node"]) == {"/listed_node"}


def test_a_gone_nodes_client_is_kept_for_the_next_process_under_its_name_and_then_dropped(graph, monkeypatch):
    """A restarted process's first calls find a client that has matched it while it started; the
    events of a gone node are not handed on until it is watched again."""
    ros, processes = graph
    events: list[str] = []
    ros._on_transition_event = lambda domain_id, fqn, msg: events.append(fqn)

    def state_of(fqn: str) -> int:
        answer = ros.loop.run_until_complete(ros.call(fqn, "get_state", GetState, GetState.Request(), 5.0))
        return answer.current_state.id

    def events_after(seconds: float) -> list[str]:
        ros.loop.run_until_complete(asyncio.sleep(seconds))  # the handed-over events run
        return events

    processes["listed_node"].spin()
    ros.watch_node("/listed_node")
    assert state_of("/listed_node") == 1
    client = ros._clients["/listed_node", "get_state"]
    processes["listed_node"].end()
    ros.forget_node("/listed_node", keep=True)  # its process ended
    processes["listed_node"] = again = Process(ros.domain_id, "listed_node").spin()  # the next one under its name
    deadline = time.monotonic() + FOUND_WITHIN_S  # the process knows the kept subscription (it matched it)
    while not again.node.count_subscribers("/listed_node/transition_event") and time.monotonic() < deadline:
        time.sleep(0.05)
    again.node.trigger_configure()  # while it is not watched again: its event is not handed on
    ros.drop_kept()  # not expired yet
    assert events_after(0.5) == [] and ros._clients["/listed_node", "get_state"] is client
    ros.watch_node("/listed_node")  # it appeared
    assert state_of("/listed_node") == 2 and ros._clients["/listed_node", "get_state"] is client
    again.node.trigger_activate()
    deadline = time.monotonic() + 5.0
    while not events_after(0.05) and time.monotonic() < deadline:
        pass
    assert events and set(events) == {"/listed_node"}  # watched again: handed on

    monkeypatch.setattr(domain_module, "KEEP_GONE_S", 0.0)
    ros.forget_node("/listed_node", keep=True)
    ros.drop_kept()  # expired: forgotten for good
    assert ("/listed_node", "get_state") not in ros._clients and "/listed_node" not in ros._event_subscriptions
