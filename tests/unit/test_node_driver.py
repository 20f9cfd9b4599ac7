"""The one way a transition is carried out (ros_gateway/node_driver.py), on real rclpy: the facts
it reports. A request's reply carries the node's new state even when a transition event reported
it first (the site's record of the node is right before the requester hears back); a run's step,
which nobody waits on, does not report that state a second time."""
from __future__ import annotations

import asyncio
import itertools
import threading
import time

import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import LifecycleNode

from ros_gateway.domain import RosDomain
from ros_gateway.node_driver import NodeDriver
from ros_gateway.parts import Core
from ros_gateway.registry import LiveNode, NodeRegistry, RobotInfo, StateChanges
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm
from tests import stack

DOMAIN_OFFSET = 3
# Each test's node has a name of its own: a client made for a name whose previous node (the
# test before, same domain) has just gone may see its first change_state go unanswered.
_node_numbers = itertools.count(1)


class DrivenNode(LifecycleNode):
    """A lifecycle node that calls ``during`` (if set) inside its configure callback."""

    during = None

    def on_configure(self, state):
        if self.during is not None:
            self.during()
        return super().on_configure(state)


class Outbox:
    """The facts going out, kept in a list; each is 'in Redis' at once."""

    def __init__(self) -> None:
        self.facts: list[dict] = []

    def emit(self, kind: str, **fields) -> dict:
        self.facts.append({"type": kind, "seq": len(self.facts) + 1, **fields})
        return self.facts[-1]

    async def delivered(self, fact: dict, timeout: float) -> bool:
        return True


@pytest.fixture
def driven(gateway_environ):
    """A lifecycle node in a process of its own (its own context), the gateway's domain, a
    registry whose state changes are reported to the outbox, and a driver."""
    domain_id = stack.domain(DOMAIN_OFFSET)
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain_id)
    name = f"driven_node_{next(_node_numbers)}"
    ros_node = DrivenNode(name, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(ros_node)
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    loop = asyncio.new_event_loop()

    def transition_event(domain_id: int, name: str, msg) -> None:  # as discovery takes them (watched nodes only)
        live = registry.nodes.get((domain_id, name))
        if live is not None:
            _, news = live.tracker.observe(int(msg.start_state.id), int(msg.goal_state.id), int(msg.transition.id))
            if news:
                registry.set_state(live, int(msg.goal_state.id))

    domain = RosDomain(domain_id, loop, on_transition_event=transition_event, on_log=lambda *a: None)
    domain.start()
    outbox = Outbox()
    registry = NodeRegistry(StateChanges(report=lambda change: outbox.emit(
        protocol.NODE_STATE, robot=change.node.robot.name, node=change.node.name, state_id=change.state_id)))
    node = LiveNode(robot=RobotInfo(1, "agv", domain_id, ""), name=f"/{name}", alive=True)
    registry.nodes[(domain_id, node.name)] = node
    driver = NodeDriver(Core(registry, {domain_id: domain}, outbox, None, 5.0), logs=None)
    try:
        yield driver, registry, node, outbox, loop, ros_node
    finally:
        domain.stop()
        loop.close()
        executor.shutdown(timeout_sec=1.0)
        ros_node.destroy_node()
        rclpy.shutdown(context=context)
        thread.join(timeout=3.0)


def transition(driver: NodeDriver, node: LiveNode, loop, label: str, start: int, *, by_reply: bool):
    async def run():
        async with node.lock:
            return await driver.transition(node, label, 5.0, source="api", known_state=start,
                                           delivered_by_reply=by_reply)
    return loop.run_until_complete(run())


def states(outbox: Outbox) -> list[int]:
    return [fact["state_id"] for fact in outbox.facts if fact["type"] == protocol.NODE_STATE]


def test_a_reply_carries_the_state_an_event_reported_first_and_a_runs_step_does_not_repeat_it(driven):
    driver, registry, node, outbox, loop, _ = driven
    registry.set_state(node, sm.INACTIVE)  # the configure's transition event came before its answer
    before = len(outbox.facts)
    result = transition(driver, node, loop, "configure", sm.UNCONFIGURED, by_reply=True)
    assert result.result.outcome == "succeeded"
    assert states(outbox)[-1:] == [sm.INACTIVE] and len(outbox.facts) == before + 2  # the state, the record
    assert [fact["type"] for fact in result.facts] == [protocol.NODE_STATE, protocol.TRANSITION]

    registry.set_state(node, sm.ACTIVE)  # the activate's event came first: reported once, here
    before = len(outbox.facts)
    result = transition(driver, node, loop, "activate", sm.INACTIVE, by_reply=False)  # a run's step
    assert result.result.outcome == "succeeded" and result.record["result_state"] == sm.ACTIVE
    assert [fact["type"] for fact in outbox.facts[before:]] == [protocol.TRANSITION]

    before = len(outbox.facts)  # no event first: the step's new state is reported, once
    result = transition(driver, node, loop, "deactivate", sm.ACTIVE, by_reply=False)
    assert [(fact["type"], fact.get("state_id")) for fact in outbox.facts[before:]] == [
        (protocol.NODE_STATE, sm.INACTIVE), (protocol.TRANSITION, None)]


def test_a_reply_handled_after_another_tools_transition_leaves_the_state_its_events_told(driven):
    """The node's events of our configure, then of another tool's activate, are handled before
    our configure's reply (the keeper undoing a rival manager saw this): the node stays active, as
    its events said, in the registry and in the state the reply carries; the record still says
    what configure did."""
    driver, registry, node, outbox, loop, ros_node = driven
    events_flowing(driver, registry, node, loop)
    registry.set_state(node, sm.UNCONFIGURED)

    def rival_activates() -> None:  # handed over to the gateway's loop, as discovery does events
        for start, goal in ((sm.INACTIVE, sm.ACTIVATING), (sm.ACTIVATING, sm.ACTIVE)):
            _, news = node.tracker.observe(start, goal, 0)
            if news:
                registry.set_state(node, goal)

    def answered_after_a_rival(request, response):
        done = answer_it(request, response)  # our configure: its events go out
        time.sleep(0.3)  # (they reach the gateway)
        loop.call_soon_threadsafe(rival_activates)
        time.sleep(0.1)
        return done

    service = next(s for s in ros_node.services if s.srv_name.endswith("/change_state"))
    answer_it, service.callback = service.callback, answered_after_a_rival
    result = transition(driver, node, loop, "configure", sm.UNCONFIGURED, by_reply=True)
    assert result.result.outcome == "succeeded" and result.record["result_state"] == sm.INACTIVE
    assert node.state_id == sm.ACTIVE
    assert [(fact["type"], fact.get("state_id")) for fact in result.facts] == [
        (protocol.NODE_STATE, sm.ACTIVE), (protocol.TRANSITION, None)]
    assert states(outbox)[-1] == sm.ACTIVE


def events_flowing(driver: NodeDriver, registry: NodeRegistry, node: LiveNode, loop) -> None:
    """Watch the node's transition events, and return once they reach the tracker (a configure
    and cleanup until one's end is seen); the node is unconfigured again."""
    driver.domains[node.robot.domain_id].watch_node(node.name)
    registry.set_state(node, sm.UNCONFIGURED)
    deadline = time.monotonic() + 10
    while True:
        result = transition(driver, node, loop, "configure", sm.UNCONFIGURED, by_reply=True)
        assert result.result.outcome == "succeeded" and result.result.message == ""  # answered: as ever
        seen = node.tracker.ended_as(sm.CONFIGURE) == sm.INACTIVE
        transition(driver, node, loop, "cleanup", sm.INACTIVE, by_reply=True)
        if seen:
            return
        assert time.monotonic() < deadline, "the node's transition events never arrived"


def test_an_answer_lost_on_the_way_is_settled_by_the_nodes_transition_events(driven):
    """DDS loses a change_state answer when the node has not yet matched the caller's answer
    reader (domain.py). The node's transition events tell the outcome all the same: the driver
    takes it from them shortly after, instead of reporting a time-out 5 s later."""
    driver, registry, node, outbox, loop, ros_node = driven
    events_flowing(driver, registry, node, loop)
    transition(driver, node, loop, "configure", sm.UNCONFIGURED, by_reply=True)

    service = next(s for s in ros_node.services if s.srv_name.endswith("/change_state"))
    answer_it, release = service.callback, threading.Event()

    def held(request, response):  # the transition runs (its events go out); the answer comes too late
        done = answer_it(request, response)
        release.wait(10)
        return done

    service.callback = held
    try:
        started = time.monotonic()
        driven_now = transition(driver, node, loop, "activate", sm.INACTIVE, by_reply=True)
        took = time.monotonic() - started
    finally:
        release.set()
    assert driven_now.result.outcome == "succeeded" and driven_now.record["result_state"] == sm.ACTIVE
    assert "answer was lost on the way" in driven_now.record["error"] and took < 3.0, took
    assert node.state_id == sm.ACTIVE
