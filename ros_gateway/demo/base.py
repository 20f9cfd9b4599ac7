"""Shared helpers for the demo lifecycle nodes.

`DemoLifecycleNode` adds to `rclpy.lifecycle.LifecycleNode`:

* `declare()`: parameter declaration with a full `ParameterDescriptor` (ranges, read-only).
* resource tracking (`own_publisher`, `own_subscription`, `own_timer`) so that
  deactivate / cleanup / shutdown / error can release everything reliably;
* a `change_state` service that answers ``success=False`` for a transition that is not
  valid in the current state (stock rclpy raises inside the executor instead, which would
  kill the whole process and leave the client without an answer);
* exception logging around every transition callback (rclpy swallows the exception);
* the read-only lifecycle services (``get_state`` ...) in their own callback group, so a
  node busy in a slow transition still reports its (transition) state.
"""

from __future__ import annotations

import threading
import weakref
from typing import Any, Callable, ClassVar, Optional

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.lifecycle.publisher import LifecyclePublisher
from rclpy.parameter import Parameter
from rclpy.subscription import Subscription
from rclpy.timer import Timer

__all__ = [
    "FAILURE",
    "SUCCESS",
    "DemoLifecycleNode",
    "LifecycleState",
    "PeriodicNode",
    "TransitionCallbackReturn",
    "declare_parameter",
]

SUCCESS = TransitionCallbackReturn.SUCCESS
FAILURE = TransitionCallbackReturn.FAILURE


def declare_parameter(
    node: Any,
    name: str,
    default: Any,
    description: str,
    *,
    min_value: Optional[float] = None,
    max_value: Optional[float] = None,
    step: Optional[float] = None,
    read_only: bool = False,
    constraints: str = "",
) -> Any:
    """Declare `name` on `node` with a descriptor; return the effective value.

    Ranges become `IntegerRange` / `FloatingPointRange` depending on the default's type.
    An integer override for a float parameter (``-p gain:=1``) is accepted as float.
    """
    ptype = Parameter.Type.from_parameter_value(default)
    descriptor = ParameterDescriptor(
        name=name,
        type=ptype.value,
        description=description,
        additional_constraints=constraints,
        read_only=read_only,
    )
    if min_value is not None and max_value is not None:
        if ptype == Parameter.Type.INTEGER:
            descriptor.integer_range = [
                IntegerRange(from_value=int(min_value), to_value=int(max_value), step=int(step or 1))
            ]
        elif ptype == Parameter.Type.DOUBLE:
            descriptor.floating_point_range = [
                FloatingPointRange(from_value=float(min_value), to_value=float(max_value), step=float(step or 0.0))
            ]
    overrides = getattr(node, "_parameter_overrides", {})
    override = overrides.get(name)
    if ptype == Parameter.Type.DOUBLE and override is not None and override.type_ == Parameter.Type.INTEGER:
        overrides[name] = Parameter(name, Parameter.Type.DOUBLE, float(override.value))
    return node.declare_parameter(name, default, descriptor).value


class DemoLifecycleNode(LifecycleNode):
    """Lifecycle node base with resource tracking and robust lifecycle services."""

    #: executor threads the robot gives this node (> 1 for nodes with slow transitions)
    EXECUTOR_THREADS: ClassVar[int] = 1

    def __init__(self, node_name: str, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self._owned: list[LifecyclePublisher | Subscription | Timer] = []
        self._abort = threading.Event()
        self._install_safe_change_state()
        self._separate_query_services()
        for state_id, callback in list(self._callbacks.items()):
            self._callbacks[state_id] = self._logged(callback)

    # -- parameters -------------------------------------------------------------------
    def declare(self, name: str, default: Any, description: str, **kwargs: Any) -> Any:
        """Declare a parameter with a descriptor (see `declare_parameter`)."""
        return declare_parameter(self, name, default, description, **kwargs)

    def param(self, name: str) -> Any:
        """Current value of a declared parameter."""
        return self.get_parameter(name).value

    # -- state ------------------------------------------------------------------------
    @property
    def state_label(self) -> str:
        """Label of the current lifecycle state (``unconfigured``, ``active`` ...)."""
        return self._state_machine.current_state[1]

    @property
    def aborting(self) -> bool:
        """True once the process is shutting down (long callbacks should stop)."""
        return self._abort.is_set()

    def request_abort(self) -> None:
        """Ask slow callbacks to return early (called on process shutdown)."""
        self._abort.set()

    # -- owned entities ---------------------------------------------------------------
    def own_publisher(self, msg_type: Any, topic: str, qos: Any) -> LifecyclePublisher:
        """Create a lifecycle publisher released by `release()`."""
        pub = self.create_lifecycle_publisher(msg_type, topic, qos)
        self._owned.append(pub)
        return pub

    def own_subscription(self, msg_type: Any, topic: str, callback: Callable, qos: Any) -> Subscription:
        """Create a subscription released by `release()`."""
        sub = self.create_subscription(msg_type, topic, callback, qos)
        self._owned.append(sub)
        return sub

    def own_timer(self, period_s: float, callback: Callable) -> Timer:
        """Create a timer released by `stop_timers()` or `release()`."""
        timer = self.create_timer(period_s, callback)
        self._owned.append(timer)
        return timer

    def stop_timers(self) -> int:
        """Destroy all owned timers; return how many were destroyed."""
        timers = [e for e in self._owned if isinstance(e, Timer)]
        for timer in timers:
            self._owned.remove(timer)
            self.destroy_timer(timer)
        return len(timers)

    def release(self) -> int:
        """Destroy every owned timer, subscription and publisher; return the count."""
        count = len(self._owned)
        while self._owned:
            entity = self._owned.pop()
            if isinstance(entity, Timer):
                self.destroy_timer(entity)
            elif isinstance(entity, Subscription):
                self.destroy_subscription(entity)
            else:
                self.destroy_lifecycle_publisher(entity)
        return count

    # -- default transition callbacks -------------------------------------------------
    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Release everything on the way to finalized."""
        count = self.release()
        self.get_logger().info(f"shutting down from {state.label}: released {count} entities, node finalized")
        return SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Recover from a failed transition by releasing everything (-> unconfigured)."""
        count = self.release()
        self.get_logger().error(
            f"error processing after a failure in a transition from {state.label}: "
            f"released {count} entities, node back to unconfigured"
        )
        return SUCCESS

    # -- internals --------------------------------------------------------------------
    def _logged(
        self, callback: Callable[[LifecycleState], TransitionCallbackReturn]
    ) -> Callable[[LifecycleState], TransitionCallbackReturn]:
        """Wrap a transition callback so an exception is logged before rclpy hides it."""

        def wrapper(state: LifecycleState) -> TransitionCallbackReturn:
            try:
                return callback(state)
            except Exception as exc:  # noqa: BLE001 - rclpy turns it into ERROR anyway
                self.get_logger().error(f"{callback.__name__} raised {type(exc).__name__}: {exc}")
                raise

        wrapper.__name__ = getattr(callback, "__name__", "callback")
        return wrapper

    def _install_safe_change_state(self) -> None:
        """Answer success=False for invalid transitions instead of raising."""
        service = getattr(self, "_service_change_state", None)
        if service is None:
            return
        original = service.callback

        def safe_change_state(request: Any, response: Any) -> Any:
            try:
                return original(request, response)
            except _rclpy.RCLError as exc:
                transition = request.transition
                self.get_logger().warn(
                    f"rejected transition id={transition.id} label={transition.label!r} "
                    f"in state {self.state_label}: {str(exc).split(',')[0]}"
                )
                response.success = False
                return response

        service.callback = safe_change_state

    def _separate_query_services(self) -> None:
        """Move get_state & co. into their own mutually exclusive callback group."""
        group = MutuallyExclusiveCallbackGroup()
        for attr in (
            "_service_get_state",
            "_service_get_available_states",
            "_service_get_available_transitions",
            "_service_get_transition_graph",
        ):
            service = getattr(self, attr, None)
            if service is None:
                continue
            service.callback_group.entities.discard(weakref.ref(service))
            service.callback_group = group
            group.add_entity(service)


class PeriodicNode(DemoLifecycleNode):
    """A node that works on a timer while active, at the rate one of its parameters sets (a
    change applies at once: the timer restarts), and publishes through ``self._pub``.

    Subclasses name the parameter (``RATE_PARAMETER``), how the log calls the rate and its unit,
    do one turn of work in ``tick()``, and register ``_on_params_set`` once their parameters are
    declared (rclpy calls it for each declaration too)."""

    RATE_PARAMETER: ClassVar[str]
    RATE_NAME: ClassVar[str] = "rate"
    RATE_UNIT: ClassVar[str] = "Hz"

    def __init__(self, node_name: str, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self._pub: Optional[LifecyclePublisher] = None
        self._timer: Optional[Timer] = None

    def tick(self) -> None:
        raise NotImplementedError

    def start_ticking(self) -> None:
        self.stop_timers()
        self._timer = self.own_timer(1.0 / self.param(self.RATE_PARAMETER), self.tick)

    def stop_ticking(self) -> None:
        self.stop_timers()
        self._timer = None

    def _on_params_set(self, params: list) -> None:
        if self._timer is not None and any(p.name == self.RATE_PARAMETER for p in params):
            self.start_ticking()
            self.get_logger().info(f"{self.RATE_NAME} now {self.param(self.RATE_PARAMETER)} {self.RATE_UNIT}")

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._pub = self._timer = None
        return super().on_shutdown(state)

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._pub = self._timer = None
        return super().on_error(state)
