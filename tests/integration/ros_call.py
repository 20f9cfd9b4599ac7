"""Stand-in for another tool (``ros2 lifecycle set``): one ChangeState call from its own process.

    python tests/integration/ros_call.py DOMAIN NODE TRANSITION_ID
"""
import sys

import rclpy
from lifecycle_msgs.srv import ChangeState


def main() -> int:
    domain, node_name, transition_id = int(sys.argv[1]), sys.argv[2], int(sys.argv[3])
    context = rclpy.context.Context()
    rclpy.init(context=context, domain_id=domain)
    node = rclpy.create_node("external_tool", context=context)
    client = node.create_client(ChangeState, f"{node_name}/change_state")
    if not client.wait_for_service(timeout_sec=10):
        print("service not available", flush=True)
        return 2
    request = ChangeState.Request()
    request.transition.id = transition_id
    future = client.call_async(request)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    executor.spin_until_future_complete(future, timeout_sec=10)
    print("success" if future.done() and future.result().success else "failure", flush=True)
    context.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
