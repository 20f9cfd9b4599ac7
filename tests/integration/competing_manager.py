"""Stand-in for another manager on the robot (a team's own bring-up script, Nav2's
lifecycle_manager): every second it activates the node if it is not active, for its own reasons.

    python tests/integration/competing_manager.py DOMAIN NODE SECONDS

Prints one line per activation it made. Sends the transition's label with its id (rclpy 7.1 ends a
node's process on an id-only request for a transition that is not valid: rclpy#1209)."""
import sys
import time

import rclpy
from lifecycle_msgs.msg import State, Transition
from lifecycle_msgs.srv import ChangeState, GetState


def call(executor, client, request, timeout: float = 5.0):
    future = client.call_async(request)
    executor.spin_until_future_complete(future, timeout_sec=timeout)
    return future.result() if future.done() else None


def main() -> int:
    domain, node_name, seconds = int(sys.argv[1]), sys.argv[2], float(sys.argv[3])
    context = rclpy.context.Context()
    rclpy.init(context=context, domain_id=domain)
    node = rclpy.create_node("competing_manager", context=context)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    get_state = node.create_client(GetState, f"{node_name}/get_state")
    change = node.create_client(ChangeState, f"{node_name}/change_state")
    if not (get_state.wait_for_service(timeout_sec=10) and change.wait_for_service(timeout_sec=10)):
        print("services not available", flush=True)
        return 2
    print("running", flush=True)
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        state = call(executor, get_state, GetState.Request())
        if state is not None and state.current_state.id == State.PRIMARY_STATE_INACTIVE:
            request = ChangeState.Request()
            request.transition.id, request.transition.label = Transition.TRANSITION_ACTIVATE, "activate"
            answer = call(executor, change, request)
            print(f"activated: {bool(answer and answer.success)}", flush=True)
        time.sleep(1.0)
    context.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
