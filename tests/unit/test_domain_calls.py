"""The gateway's service calls on real rclpy (RosDomain.call): a read that goes unanswered is
asked again and the first answer counts; a call that changes a node is sent once, whatever
happens. The server here holds its first request unanswered, which is how a request whose
response Fast DDS dropped looks to the caller (the response writer had not matched the
caller's reader yet: "client will not receive response")."""
from __future__ import annotations

import asyncio
import threading
import time

import pytest
import rclpy
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor

from ros_gateway import domain as domain_module
from ros_gateway.domain import RosDomain, ServiceTimeout
from tests import stack

DOMAIN_OFFSET = 1
HELD_S = 3.0  # how long the server sits on its first request of each kind


class HoldingServer:
    """GetState and ChangeState servers that answer their first request after HELD_S and the
    others at once; they count what they receive."""

    def __init__(self, domain_id: int) -> None:
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node("held_node", context=self.context)
        group = ReentrantCallbackGroup()
        self.received = {"get_state": 0, "change_state": 0}
        self.lock = threading.Lock()
        self.idle = threading.Condition(self.lock)
        self.busy = 0  # requests being answered
        self.node.create_service(GetState, "/held_node/get_state", self._get_state, callback_group=group)
        self.node.create_service(ChangeState, "/held_node/change_state", self._change_state, callback_group=group)
        self.executor = MultiThreadedExecutor(num_threads=4, context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def _answer(self, service: str, response):
        with self.lock:
            self.received[service] += 1
            first = self.received[service] == 1
            self.busy += 1
        try:
            if first:
                time.sleep(HELD_S)
            return response
        finally:
            with self.lock:
                self.busy -= 1
                self.idle.notify_all()

    def _get_state(self, request, response):
        response.current_state.id = 1
        response.current_state.label = "unconfigured"
        return self._answer("get_state", response)

    def _change_state(self, request, response):
        response.success = True
        return self._answer("change_state", response)

    def stop(self) -> None:
        with self.lock:  # a held request is answered before the server goes
            self.idle.wait_for(lambda: self.busy == 0, timeout=HELD_S + 1)
        self.executor.shutdown(timeout_sec=2.0)
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)
        self.thread.join(timeout=3.0)


@pytest.fixture
def server_and_domain(gateway_environ):
    domain_id = stack.domain(DOMAIN_OFFSET)
    server = HoldingServer(domain_id)
    loop = asyncio.new_event_loop()
    ros = RosDomain(domain_id, loop, on_transition_event=lambda *a: None, on_log=lambda *a: None)
    ros.start()
    try:
        yield server, ros, loop
    finally:
        ros.stop()
        loop.close()
        server.stop()


def timed(loop: asyncio.AbstractEventLoop, call) -> tuple[object, float]:
    began = time.monotonic()
    answer = loop.run_until_complete(call)
    return answer, time.monotonic() - began


def test_an_unanswered_read_is_asked_again_and_the_first_answer_counts(server_and_domain):
    server, ros, loop = server_and_domain
    answer, took = timed(loop, ros.call("/held_node", "get_state", GetState, GetState.Request(), 5.0))
    assert answer.current_state.label == "unconfigured"
    # Asked again after RESEND_AFTER_S; that request is answered at once, not after HELD_S.
    assert domain_module.RESEND_AFTER_S <= took < HELD_S - 0.5
    assert server.received["get_state"] == 2


def test_a_read_that_never_gets_an_answer_still_ends_at_its_timeout(server_and_domain, monkeypatch):
    server, ros, loop = server_and_domain
    monkeypatch.setattr(domain_module, "RESEND_AFTER_S", 10.0)  # no second request within the bound
    began = time.monotonic()
    with pytest.raises(ServiceTimeout, match="did not answer within 1 s"):
        loop.run_until_complete(ros.call("/held_node", "get_state", GetState, GetState.Request(), 1.0))
    assert 1.0 <= time.monotonic() - began < 1.5
    assert server.received["get_state"] == 1


def test_a_change_is_sent_once_even_when_its_answer_is_slow(server_and_domain):
    server, ros, loop = server_and_domain
    request = ChangeState.Request()
    request.transition.id = 1
    answer, took = timed(loop, ros.call("/held_node", "change_state", ChangeState, request, 5.0))
    assert answer.success is True
    assert took >= HELD_S - 0.1  # waited for the one request's answer
    assert server.received["change_state"] == 1
