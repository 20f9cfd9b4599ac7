"""How often a topic is published, measured by the gateway (ros_gateway/topic_rates.py) on real
rclpy: a publisher of the test's own whose rate changes is followed, the site told when the rate
moved (not every second), and a topic no config asks for any more is let go."""
from __future__ import annotations

import asyncio
import threading

import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from std_msgs.msg import String

from ros_gateway import topic_rates
from ros_gateway.domain import RosDomain
from ros_gateway.registry import NodeRegistry, RobotInfo, StateChanges
from ros_gateway.topic_rates import TopicRates
from tests import stack

DOMAIN_OFFSET = 43


class Outbox:
    def __init__(self) -> None:
        self.facts: list[dict] = []

    def emit(self, kind: str, **fields) -> dict:
        self.facts.append({"type": kind, **fields})
        return self.facts[-1]


@pytest.fixture
def publisher(gateway_environ):
    """/chatter published every ``period[0]`` seconds from a context of its own."""
    domain_id = stack.domain(DOMAIN_OFFSET)
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain_id)
    node = rclpy.create_node("chatter_source", context=context)
    pub = node.create_publisher(String, "/chatter", 10)
    period = [0.05]
    stop = threading.Event()

    def publish() -> None:
        while not stop.wait(period[0]):
            pub.publish(String(data="hi"))

    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    threads = [threading.Thread(target=publish, daemon=True), threading.Thread(target=executor.spin, daemon=True)]
    for thread in threads:
        thread.start()
    try:
        yield domain_id, period
    finally:
        stop.set()
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        rclpy.shutdown(context=context)
        for thread in threads:
            thread.join(timeout=3.0)


def test_a_rate_is_measured_followed_as_it_changes_and_let_go(publisher, monkeypatch):
    monkeypatch.setattr(topic_rates, "RESEND_S", 1000.0)
    domain_id, period = publisher
    outbox = Outbox()

    async def scenario() -> None:
        domain = RosDomain(domain_id, asyncio.get_running_loop(), on_transition_event=lambda *a: None,
                           on_log=lambda *a: None)
        domain.start()
        try:
            registry = NodeRegistry(StateChanges())
            registry.robots[1] = RobotInfo(1, "agv", domain_id, "")
            rates = TopicRates(registry, {domain_id: domain}, outbox)
            rates.apply({"robots": [{"id": 1, "rates": [{"topic": "/chatter", "window_s": 1.0},
                                                         {"topic": "/nobody", "window_s": 1.0}]}]})

            async def measured(low: float, high: float, seconds: float = 8.0) -> float:
                for _ in range(int(seconds / 0.25)):
                    await rates.report()
                    hz = outbox.facts[-1]["rates"][0]["hz"] if outbox.facts else None
                    if hz is not None and low <= hz <= high:
                        return hz
                    await asyncio.sleep(0.25)
                raise AssertionError(f"no rate within {low}..{high} Hz: {outbox.facts[-3:]}")

            await measured(14.0, 24.0)  # 20 Hz
            assert outbox.facts[-1]["rates"][1] == {"topic": "/nobody", "hz": None, "window_s": 1.0}
            sent = len(outbox.facts)
            for _ in range(4):  # steady: nothing new to say
                await rates.report()
            assert len(outbox.facts) == sent
            period[0] = 0.25
            await measured(2.5, 5.5)  # 4 Hz
            rates.apply({"robots": [{"id": 1}]})
            assert rates.meters == {} and list(domain.meter_node().subscriptions) == []
        finally:
            domain.stop()

    asyncio.run(scenario())
