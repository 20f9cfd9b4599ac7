"""One lifecycle transition from a fresh process, the way ``ros2 lifecycle set`` works:
start Python, import rclpy, join the domain, discover the service, call once, exit.

    python tests/benchmarks/one_shot.py DOMAIN NODE TRANSITION_ID    (exit 0 on success)
"""
import sys

import rclpy
from lifecycle_msgs.srv import ChangeState
from rclpy.executors import SingleThreadedExecutor


def main(domain: int, node_name: str, transition_id: int) -> int:
    context = rclpy.context.Context()
    rclpy.init(context=context, domain_id=domain)
    node = rclpy.create_node("lifecycle_set_once", context=context, start_parameter_services=False)
    client = node.create_client(ChangeState, f"{node_name}/change_state")
    if not client.wait_for_service(timeout_sec=20):
        return 2
    request = ChangeState.Request()
    request.transition.id = transition_id
    future = client.call_async(request)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    executor.spin_until_future_complete(future, timeout_sec=20)
    ok = future.done() and future.result().success
    node.destroy_node()
    context.try_shutdown()
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main(int(sys.argv[1]), sys.argv[2], int(sys.argv[3])))
