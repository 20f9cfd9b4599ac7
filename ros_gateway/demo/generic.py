"""Minimal lifecycle node for scale benchmarks: no timers, no topics, two parameters."""

from __future__ import annotations

from typing import Any

from .base import SUCCESS, DemoLifecycleNode, LifecycleState, TransitionCallbackReturn


class GenericNode(DemoLifecycleNode):
    """Cheap lifecycle node that only logs one line per transition."""

    def __init__(self, node_name: str, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.declare("max_count", 10, "An integer setting", min_value=0, max_value=1000)
        self.declare("gain", 1.0, "A floating point setting", min_value=0.0, max_value=10.0)

    def _transition(self, what: str, state: LifecycleState) -> TransitionCallbackReturn:
        self.get_logger().info(f"{what} (from {state.label})")
        return SUCCESS

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Log only."""
        return self._transition("configured", state)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Log only."""
        return self._transition("activated", state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Log only."""
        return self._transition("deactivated", state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Log only."""
        return self._transition("cleaned up", state)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Log only."""
        return self._transition("shut down", state)

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Log only; recover to unconfigured."""
        self.get_logger().error(f"error processing (from {state.label}): recovering")
        return SUCCESS
