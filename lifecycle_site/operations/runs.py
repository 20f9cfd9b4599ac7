"""Starting and following ordered group operations (GroupRun), for the API, pages and CLI.

The site records the run and hands the robot's gateway its nodes in tiers (the bring-up
order); the gateway carries it out step by step, reports each node's result as "run" facts
(stored by the ingest process) and pushes progress to the robot's group.
"""
from __future__ import annotations

import time
import uuid

from django.db.models import F
from django.utils.translation import gettext as _

from lifecycle_site.fleet import roles
from lifecycle_site.fleet.models import GroupRun, ManagedNode, Robot
from lifecycle_site.gateway_link.gateway_client import GatewayError, call_gateway
from lifecycle_site.ingest import verdicts
from lifecycle_site.refusal import Refusal
from ros_gateway.shared import operations, protocol

MAX_WAIT_S = 600.0


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
    """Record a run and hand it to the gateway; returns at once (the run goes on there). What
    cannot start is a Refusal (nothing recorded, but for a gateway that did not take the run)."""
    known = operations.get(operation)
    if known is None or not known.startable:
        raise Refusal("unknown_operation", _("%(operation)s is not an operation; use one of %(operations)s.") % {
            "operation": repr(operation), "operations": ", ".join(operations.names())})
    may_start(robot, known, None, user, policy)
    nodes = list(nodes or [])
    unknown = [n for n in nodes if not ManagedNode.objects.filter(robot=robot, name=n).exists()]
    if unknown:
        raise Refusal("not_found", _("%(robot)s has no node %(nodes)s.") % {
            "robot": robot.name, "nodes": ", ".join(unknown)}, 404)
    if known.scope == operations.NODE and len(nodes) != 1:
        raise Refusal("invalid_field", _("%(operation)s works on exactly one node.") % {"operation": operation})
    return launch(robot, operation, user=user, source=source, policy=policy, node_timeout=node_timeout, nodes=nodes)


def may_start(robot: Robot, known: operations.Operation, needs: str | None, user, policy: str) -> None:
    """A run of ``known`` on ``robot`` by ``user`` with ``policy``, or the Refusal saying why not
    (``needs``: the refusal for a user without the role, "Applying a mode needs the %(role)s role.";
    None: "Bring up needs the operator role.", by the operation's button)."""
    if getattr(user, "pk", None) and not roles.may_act_as(user, known.role):
        if needs is None:  # the button's word (ros_gateway/shared/operations.py), as the pages translate it
            text = _("%(action)s needs the %(role)s role.") % {"action": _(known.button), "role": role_name(known.role)}
        else:
            text = str(needs) % {"role": role_name(known.role)}
        raise Refusal("forbidden", text, 403)
    if policy not in GroupRun.Policy.values:
        raise Refusal("invalid_field", _("policy must be 'stop' (at the first failure) or 'continue'."))
    if not robot.enabled:
        raise Refusal("robot_disabled", _("Robot %(robot)s is disabled; enable it first.") % {"robot": robot.name}, 409)


def role_name(role: str) -> str:
    """A role as a refusal names it ("operator", "admin", "viewer")."""
    return {"operator": _("operator"), "admin": _("admin"), "viewer": _("viewer")}.get(role, role)


def launch(robot: Robot, operation: str, *, user, source: str, policy: str, node_timeout: float,
           nodes: list[str], plan: dict | None = None) -> GroupRun:
    """Record a run whose request was checked and hand it to the gateway. ``plan``: a mode's
    (its name, each node's target and parameters), kept with the run and sent with it."""
    order = tiers(robot, nodes)
    run = GroupRun.objects.create(
        id=uuid.uuid4().hex,
        robot=robot,
        operation=operation,
        policy=policy,
        node_timeout=node_timeout,
        only_nodes=nodes,
        steps=len(order),
        requested_by=user if getattr(user, "pk", None) else None,
        source=source,
        plan=plan or {},
    )
    spec = {
        "id": run.id, "robot": robot.name, "operation": operation, "policy": policy, "node_timeout": node_timeout,
        "tiers": order, "source": source, "user_id": run.requested_by_id,
        **({"targets": plan["targets"], "parameters": plan["parameters"]} if plan else {}),
    }
    try:
        call_gateway(robot.gateway.name, protocol.START_RUN, timeout=2.0, run=spec)
    except GatewayError as exc:
        # The gateway may have taken the run all the same (no answer in time): it must not go on.
        # (stored and sent in English: the run's summary, whoever reads it)
        verdicts.publish(robot.gateway.name, [run.id], GroupRun.Status.FAILED, exc.english)
        GroupRun.objects.filter(pk=run.pk).update(status=GroupRun.Status.FAILED, message=exc.english)
        raise
    return run


def tiers(robot: Robot, only: list[str]) -> list[list[str]]:
    """The robot's bring-up order as tiers run one after the other: one tier per position
    (nodes sharing a position go together), then every node without a position. Nodes within
    a tier have no order between them. ``only`` narrows the run to those nodes. The gateway
    runs the tiers in reverse for the operations that go down (pause, reset, shut down).

    A whole-robot run leaves out names watched but never seen (a node not started yet): it
    would fail there and, with the "stop" policy, stop the run for the nodes that are up."""
    rows = ManagedNode.objects.filter(robot=robot).order_by(F("order").asc(nulls_last=True), "name")
    if not only:
        rows = rows.exclude(alive=False, last_seen__isnull=True)  # "waiting" on the pages
    wanted = set(only)
    by_position: dict[int | None, list[str]] = {}
    for name, position in rows.values_list("name", "order"):
        if not only or name in wanted:
            by_position.setdefault(position, []).append(name)
    listed = {name for tier in by_position.values() for name in tier}
    # Named but unknown by now (removed meanwhile): still reported, as "not running".
    missing = [name for name in only if name not in listed]
    return [*by_position.values(), *([missing] if missing else [])]


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
