"""A gateway executor goes on after a failure inside a spin (ros_gateway/domain.py, _spin): a
thread that ended there left every node on its shard unanswered until the gateway restarted (seen
when a supervised process of 50 nodes stopped: their entities were destroyed while it waited)."""
from __future__ import annotations

import logging
import threading
import time

import rclpy
from rclpy.executors import SingleThreadedExecutor

from ros_gateway.domain import _spin
from tests import stack

DOMAIN_OFFSET = 37


def test_an_executor_spins_on_after_a_callback_fails(gateway_environ, caplog):
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=stack.domain(DOMAIN_OFFSET))
    node = rclpy.create_node("spin_test", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    calls = []

    def tick() -> None:
        calls.append(time.monotonic())
        if len(calls) == 1:
            raise RuntimeError("a destroyed entity's handle (as rclpy's InvalidHandle)")

    node.create_timer(0.05, tick)
    thread = threading.Thread(target=_spin, args=(executor, 99), daemon=True)
    try:
        with caplog.at_level(logging.WARNING, logger="ros_gateway.domain"):
            thread.start()
            stack.wait_for(lambda: len(calls) >= 5, 5, "the timer to fire again after its failure")
        assert thread.is_alive()
        assert "an executor of ROS domain 99 failed (1 time(s) in 10 s); spinning on" in caplog.text
    finally:
        executor.shutdown(timeout_sec=2.0)
        node.destroy_node()
        rclpy.shutdown(context=context)
        thread.join(timeout=3.0)
    assert not thread.is_alive()  # and it ends with the domain
