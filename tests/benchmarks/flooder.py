"""A lifecycle node that logs as fast as it can, or at a given rate, when told to (JSON lines on stdin).

    python -m tests.benchmarks.flooder DOMAIN NODE_NAME
    -> {"op": "flood", "seconds": 10, "via": "rosout", "rate": 0}   <- {"sent": 123456, "seconds": 10.0}

``via: "rosout"`` (the scenario's way) publishes rcl_interfaces/Log records on /rosout under
the node's logger name with rcl's own /rosout QoS, which is what rcutils does for a C++ node:
rclpy's ``logger.info`` alone costs about 0.5 ms a call (it inspects the caller's frame), so a
Python node cannot log faster than about 2,000 records/s. ``via: "logger"`` measures that.
Console output is off (``--disable-stdout-logs``) either way.
"""
from __future__ import annotations

import json
import sys
import threading
import time

import rclpy
from rcl_interfaces.msg import Log
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.lifecycle import LifecycleNode
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

BURST = 200
TEXT = "flood record {}: motor current 3.2 A, wheel speed 0.87 m/s, all nominal"
# rcl_qos_profile_rosout_default: what every node's /rosout publisher uses.
ROSOUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL, lifespan=Duration(seconds=10))


def flood(node: LifecycleNode, rosout, seconds: float, via: str = "rosout", rate: float = 0.0) -> dict:
    """Log for ``seconds``: as fast as possible, or ``rate`` records per second (in bursts of
    BURST, each sent when it is due)."""
    logger = node.get_logger()
    clock = node.get_clock()
    sent = 0
    began = time.monotonic()
    end = began + seconds
    while (now := time.monotonic()) < end:
        if rate > 0:
            due = began + sent / rate
            if due > now:
                time.sleep(min(due, end) - now)
                continue
        for _ in range(BURST):
            if via == "logger":
                logger.info(TEXT.format(sent))
            else:
                rosout.publish(Log(stamp=clock.now().to_msg(), level=Log.INFO, name=logger.name,
                                   msg=TEXT.format(sent), file="flooder.py", function="flood", line=42))
            sent += 1
    return {"sent": sent, "seconds": time.monotonic() - began, "began": began}


def main(domain: int, name: str) -> int:
    context = Context()
    rclpy.init(args=["flooder", "--ros-args", "--disable-stdout-logs", "--disable-external-lib-logs"],
               context=context, domain_id=domain)
    node = LifecycleNode(name, context=context)
    # Made now, so that the gateway's subscription has matched it before the flood begins.
    rosout = node.create_publisher(Log, "/rosout", ROSOUT_QOS)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)

    def spin() -> None:
        try:
            executor.spin()
        except ExternalShutdownException:
            pass

    threading.Thread(target=spin, daemon=True).start()
    print(json.dumps({"ready": True}), flush=True)
    for line in sys.stdin:
        command = json.loads(line)
        if command.get("op") != "flood":
            break
        print(json.dumps(flood(node, rosout, float(command["seconds"]), command.get("via", "rosout"),
                               float(command.get("rate", 0.0)))), flush=True)
    executor.shutdown(timeout_sec=1.0)
    node.destroy_node()
    context.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main(int(sys.argv[1]), sys.argv[2]))
