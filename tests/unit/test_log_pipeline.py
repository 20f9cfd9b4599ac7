"""The gateway's log collector (ros_gateway/logs.py): a record from a ROS thread after a quiet
spell goes out at once, a burst goes out in few batches, and quiet logs do not wake the loop."""
from __future__ import annotations

import asyncio
import threading
import time

from rcl_interfaces.msg import Log

from ros_gateway import logs
from ros_gateway.registry import NodeRegistry, RobotInfo, StateChanges


class Sink:
    """Where the pipeline's batches go (the outbox to Redis in the gateway)."""

    def __init__(self) -> None:
        self.batches: list[tuple[list, float]] = []

    def emit_logs(self, rows: list, dropped: int = 0) -> None:
        self.batches.append((rows, time.monotonic()))


def test_records_wake_the_collector_and_quiet_costs_no_wake_up():
    registry = NodeRegistry(StateChanges())
    robot = RobotInfo(1, "agv", 5, "", True)
    registry.robots[robot.id] = robot
    registry.appeared(5, robot, "/camera_driver", frozenset())
    sink = Sink()
    pipeline = logs.LogPipeline(registry, sink, buffer_limit=100)
    collected: list[int] = []
    real_collect = pipeline.collect

    def counted() -> None:
        collected.append(1)
        real_collect()

    pipeline.collect = counted

    def from_a_ros_thread(text: str, count: int = 1) -> float:
        sent = time.monotonic()
        thread = threading.Thread(target=lambda: [pipeline.on_log(5, Log(name="camera_driver", msg=text, level=20))
                                                  for _ in range(count)])
        thread.start()
        thread.join()
        return sent

    async def scenario() -> None:
        stopping = asyncio.Event()
        runner = asyncio.create_task(pipeline.run(stopping))
        await asyncio.sleep(1.0)  # quiet: one look at the start, then asleep (it looked every 0.1 s)
        assert len(collected) <= 2 and not sink.batches
        sent = await asyncio.to_thread(from_a_ros_thread, "after a quiet spell")
        while not sink.batches and time.monotonic() - sent < 1.0:
            await asyncio.sleep(0.005)
        assert sink.batches and sink.batches[0][1] - sent < 0.5  # woken (asleep, it would wait 5 s)
        await asyncio.to_thread(from_a_ros_thread, "burst", 50)
        await asyncio.sleep(0.3)
        stopping.set()
        runner.cancel()

    asyncio.run(scenario())
    rows = [row for batch, _ in sink.batches for row in batch]
    assert [row[5] for row in rows] == ["after a quiet spell"] + ["burst"] * 50
    assert len(sink.batches) <= 3  # the burst in one or two batches
