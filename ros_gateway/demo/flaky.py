"""A lifecycle node that fails on purpose, to exercise a supervisor's error handling.

``failure_mode`` (read at transition time, so it can be changed between transitions):

* ``none``: behaves (DEBUG heartbeat every 5 s while active);
* ``fail_configure``: on_configure returns FAILURE -> stays unconfigured;
* ``raise_activate``: on_activate raises -> errorprocessing -> on_error SUCCESS
  -> unconfigured;
* ``error_in_error``: on_activate raises and on_error returns FAILURE -> finalized;
* ``crash``: on_activate logs FATAL and kills the process with ``os._exit(3)``;
* ``slow_configure``: on_configure sleeps ``slow_seconds`` then succeeds;
* ``hang``: on_configure never returns (a driver that never answers): the node stays
  ``configuring``, and its process does not even end on SIGINT (the stuck thread keeps it), so
  only restarting the process helps, with SIGKILL after the stop signal's grace.

Its diagnostics status ``flaky_node: Driver`` follows ``failure_mode``: ``none`` is OK; a failing
mode is WARN at first and ERROR once it lasted `ESCALATE_AFTER_S`; ``slow_configure`` (slow, but it
succeeds) stays WARN.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from typing import Any, Optional

from rcl_interfaces.msg import SetParametersResult

from .base import FAILURE, SUCCESS, DemoLifecycleNode, LifecycleState, TransitionCallbackReturn
from .diagnostics import ERROR, OK, WARN, Report, StatusPublisher

FAILURE_MODES = ("none", "fail_configure", "raise_activate", "error_in_error", "crash", "slow_configure", "hang")
CRASH_EXIT_CODE = 3
ESCALATE_AFTER_S = 3.0
FAILURE_REASONS = {
    "fail_configure": "hardware not found on /dev/ttyFLAKY",
    "raise_activate": "driver fault while activating",
    "error_in_error": "driver fault, error recovery failing",
    "crash": "motor driver unstable, process may crash",
    "slow_configure": "slow firmware upload",
    "hang": "driver not answering",
}


class FlakyNode(DemoLifecycleNode):
    """Lifecycle node whose transitions fail according to ``failure_mode``."""

    EXECUTOR_THREADS = 2  # get_state answers ``configuring`` during slow_configure

    def __init__(self, node_name: str = "flaky_node", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.add_on_set_parameters_callback(self._validate)
        self.declare(
            "failure_mode", "none", "How the next transitions fail", constraints="one of: " + ", ".join(FAILURE_MODES)
        )
        self.declare(
            "slow_seconds", 8.0, "Duration of on_configure in slow_configure mode", min_value=0.0, max_value=120.0
        )
        self._beats = 0
        self._seen_mode: Optional[str] = None
        self._mode_since = 0.0
        self.diagnostics = StatusPublisher(
            self, "/dev/ttyFLAKY", {"Driver": self._driver_status}, alive=lambda: self.state_label != "finalized"
        )
        self.get_logger().info(f"created (unconfigured), failure_mode={self.mode}")

    @property
    def mode(self) -> str:
        """Current failure mode."""
        return self.param("failure_mode")

    def _validate(self, params: list) -> SetParametersResult:
        for p in params:
            if p.name == "failure_mode" and p.value not in FAILURE_MODES:
                reason = f"unknown failure_mode {p.value!r}; expected one of: " + ", ".join(FAILURE_MODES)
                self.get_logger().warn(f"rejected parameter: {reason}")
                return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Fail, stall or succeed depending on ``failure_mode``."""
        log = self.get_logger()
        mode = self.mode
        if mode == "fail_configure":
            log.error(
                "configure failed: simulated hardware not found on /dev/ttyFLAKY "
                "(failure_mode=fail_configure); staying unconfigured"
            )
            return FAILURE
        if mode == "hang":
            log.error("configure hangs: the simulated driver never answers (failure_mode=hang); only restarting "
                      "the process helps")
            threading.Event().wait()  # never set: this callback never returns
        if mode == "slow_configure":
            seconds = self.param("slow_seconds")
            log.info(f"configuring slowly: simulated firmware upload takes {seconds:.1f} s")
            deadline = time.monotonic() + seconds
            while not self.aborting:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                log.debug(f"firmware upload: {left:.1f} s left", throttle_duration_sec=2.0)
                self._abort.wait(min(left, 1.0))
            if self.aborting:
                log.warn("slow configure interrupted by process shutdown")
                return FAILURE
        log.info(f"configured (failure_mode={mode})")
        return SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Raise, crash the process or start a heartbeat depending on ``failure_mode``."""
        log = self.get_logger()
        mode = self.mode
        if mode in ("raise_activate", "error_in_error"):
            raise RuntimeError(f"simulated driver fault while activating (failure_mode={mode})")
        if mode == "crash":
            log.fatal(f"simulated segmentation fault in the motor driver: process exits with code {CRASH_EXIT_CODE}")
            sys.stdout.flush()
            sys.stderr.flush()
            time.sleep(0.3)  # let the FATAL record reach /rosout
            os._exit(CRASH_EXIT_CODE)
        result = super().on_activate(state)
        self._beats = 0
        self.own_timer(5.0, self._heartbeat)
        log.info("activated: heartbeat every 5 s")
        return result

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Stop the heartbeat."""
        self.stop_timers()
        self.get_logger().info(f"deactivated after {self._beats} heartbeats")
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Nothing held while inactive; just report."""
        count = self.release()
        self.get_logger().info(f"cleaned up: released {count} entities")
        return SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Recover (-> unconfigured) unless ``failure_mode`` is ``error_in_error``."""
        self.release()
        if self.mode == "error_in_error":
            self.get_logger().error(
                f"error recovery after failed transition from {state.label} failed too "
                "(failure_mode=error_in_error): node will be finalized"
            )
            return FAILURE
        self.get_logger().warn(f"recovered from failed transition from {state.label}: back to unconfigured")
        return SUCCESS

    def _heartbeat(self) -> None:
        self._beats += 1
        self.get_logger().debug(f"heartbeat #{self._beats}, failure_mode={self.mode}")

    def _driver_status(self) -> Report:
        now, mode = time.monotonic(), self.mode
        if mode != self._seen_mode:
            self._seen_mode, self._mode_since = mode, now
        values: dict[str, Any] = {"failure_mode": mode, "state": self.state_label, "failing_for_s": 0.0}
        if mode == "none":
            return OK, "driver OK", values
        failing = now - self._mode_since
        values["failing_for_s"] = failing
        # (- 0.1: the status seen 3 ticks after the change may come a few ms early)
        level = ERROR if mode != "slow_configure" and failing >= ESCALATE_AFTER_S - 0.1 else WARN
        return level, f"{FAILURE_REASONS.get(mode, 'driver failing')} (failure_mode={mode})", values
