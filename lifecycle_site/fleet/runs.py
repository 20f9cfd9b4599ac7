"""Starting and following ordered group operations (GroupRun), for the API, pages and CLI.

The site records the run, the gateway carries it out step by step (ros_gateway/groups.py),
writing each node's result into the run and pushing progress to the robot's group.
"""
from __future__ import annotations

import time
import uuid

from lifecycle_site.fleet.gateway_client import GatewayError, call_gateway
from lifecycle_site.fleet.models import GroupRun, ManagedNode, Robot
from ros_gateway.shared import protocol

OPERATIONS = [choice for choice, _ in GroupRun.Operation.choices if choice != "recover"]
MAX_WAIT_S = 600.0


class RunRefused(Exception):
    """The run cannot start; ``code`` and ``message`` are shown to the user."""

    def __init__(self, code: str, message: str, status: int = 400) -> None:
        super().__init__(message)
        self.code, self.message, self.status = code, message, status


def start_run(
    robot: Robot,
    operation: str,
    *,
    user,
    source: str,
    policy: str = GroupRun.Policy.STOP,
    node_timeout: float = 5.0,
    nodes: list[str] | None = None,
) -> GroupRun:
    """Record a run and hand it to the gateway; returns at once (the run goes on there)."""
    if operation not in OPERATIONS:
        raise RunRefused("unknown_operation", f"{operation!r} is not an operation; use one of {', '.join(OPERATIONS)}.")
    if policy not in GroupRun.Policy.values:
        raise RunRefused("invalid_field", "policy must be 'stop' (at the first failure) or 'continue'.")
    if not robot.enabled:
        raise RunRefused("robot_disabled", f"Robot {robot.name} is disabled; enable it first.", 409)
    nodes = list(nodes or [])
    unknown = [n for n in nodes if not ManagedNode.objects.filter(robot=robot, name=n).exists()]
    if unknown:
        raise RunRefused("not_found", f"{robot.name} has no node {', '.join(unknown)}.", 404)
    if operation == "restart" and len(nodes) != 1:
        raise RunRefused("invalid_field", "restart works on exactly one node.")
    run = GroupRun.objects.create(
        id=uuid.uuid4().hex,
        robot=robot,
        operation=operation,
        policy=policy,
        node_timeout=node_timeout,
        only_nodes=nodes,
        requested_by=user if getattr(user, "pk", None) else None,
        source=source,
    )
    try:
        call_gateway(protocol.START_RUN, timeout=2.0, run_id=run.id)
    except GatewayError as exc:
        GroupRun.objects.filter(pk=run.pk).update(status=GroupRun.Status.FAILED, message=exc.message)
        raise RunRefused(exc.code, exc.message, exc.status) from None
    return run


def wait_for(run: GroupRun, seconds: float, on_progress=None) -> GroupRun:
    """Re-read the run until it is done or ``seconds`` have passed (bounded)."""
    deadline = time.monotonic() + min(max(seconds, 0.0), MAX_WAIT_S)
    seen = -1
    while True:
        run.refresh_from_db()
        if on_progress is not None and len(run.results) != seen:
            seen = len(run.results)
            on_progress(run)
        if run.done or time.monotonic() >= deadline:
            return run
        time.sleep(0.1)
