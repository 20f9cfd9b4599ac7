"""/rosout read by a thread of its own (ros_gateway/rosout_reader.py), over real DDS: every
message reaches the gateway's hand-over, and a quiet /rosout costs nothing (the thread sleeps
until a message comes or ``stop()`` wakes it, well before its 5 s safeguard)."""
from __future__ import annotations

import time

import rclpy
from rcl_interfaces.msg import Log

from ros_gateway.rosout_reader import ROSOUT_QOS, RosoutReader
from tests import stack

DOMAIN_OFFSET = 39


def wake_ups(native_id: int) -> int:
    """How often the thread went to sleep and was woken (its voluntary context switches)."""
    with open(f"/proc/self/task/{native_id}/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("voluntary_ctxt_switches"))


def test_messages_arrive_a_quiet_rosout_costs_nothing_and_stop_is_prompt(gateway_environ):
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=stack.domain(DOMAIN_OFFSET))
    reading = rclpy.create_node("rosout_reader_test", context=context)
    writing = rclpy.create_node("rosout_writer_test", context=context)
    publisher = writing.create_publisher(Log, "/rosout", ROSOUT_QOS)
    got: list[tuple[int, str]] = []
    reader = RosoutReader(reading, 42, lambda domain, msg: got.append((domain, msg.msg)))
    try:
        reader.start()
        stack.wait_for(lambda: publisher.get_subscription_count() > 0, 10, "the reader to match the publisher")
        for i in range(3):
            publisher.publish(Log(name="writer", msg=f"line {i}", level=20))
        stack.wait_for(lambda: len(got) == 3, 5, "three /rosout messages handed over")
        assert got == [(42, "line 0"), (42, "line 1"), (42, "line 2")]

        # Quiet: the thread waits (it used to wake every 0.1 s: 15 times here).
        before = wake_ups(reader._thread.native_id)
        time.sleep(1.5)
        assert wake_ups(reader._thread.native_id) - before <= 2
        began = time.monotonic()
        reader.stop()
        assert not reader._thread.is_alive() and time.monotonic() - began < 1.0
    finally:
        reader.stop(timeout=0.1)
        writing.destroy_node()
        reading.destroy_node()
        rclpy.shutdown(context=context)
