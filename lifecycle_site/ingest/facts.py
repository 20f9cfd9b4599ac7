"""What gateways report, written to the database: the one place that does it.

``apply_facts`` is called by the ingest process for every fact it reads from a gateway's
stream, and by the request path for the facts that come back with a reply (so the audit
record exists before the user has the answer). Applying a fact twice has the effect of
applying it once: audit records are keyed by the fact's id, states carry their time.
Fact shapes: ros_gateway/shared/protocol.py and the wire contract in docs/architecture.md.
"""
from __future__ import annotations

import logging
from datetime import datetime
from typing import Any, Iterable

from django.db import InterfaceError, OperationalError, transaction
from django.db.models import Q
from django.db.models.functions import Coalesce

from lifecycle_site.audit.models import ParameterRecord, TransitionRecord
from lifecycle_site.fleet.models import GroupRun, ManagedNode
from lifecycle_site.gateway_link import attribution
from lifecycle_site.gateway_link import gateway_input as checks
from lifecycle_site.gateway_link.gateway_input import FactRejected
from lifecycle_site.ingest import state_chain, verdicts
from lifecycle_site.ingest.absences import node_back, node_left
from lifecycle_site.ingest.diagnostic_facts import apply_diagnostics
from lifecycle_site.ingest.fact_context import Applied, Hints, KnownRecords, save_once
from lifecycle_site.ingest.keep_facts import apply_enforcement_stopped, apply_topic_rates
from lifecycle_site.ingest.process_facts import apply_node_process, apply_process
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm

log = logging.getLogger(__name__)
# Why a node.gone fact says a node went (ros_gateway/liveness.py, processes.py); anything else counts as "".
GONE_REASONS = ("unreachable", protocol.PROCESS_LOST)
# A transition record with this outcome moves the node's process status (a loss comes as node.gone).
PROCESS_STATUS = {protocol.PROCESS_RESTARTED: "restarted"}

# PostgreSQL's codes for "your transaction lost a conflict with another; run it again".
CONFLICT_STATES = {"40P01", "40001"}
CONFLICT_ATTEMPTS = 3
ROBOT_NODES_LIMIT = 5000  # nodes of one robot a robot.nodes fact may list


def apply_facts(gateway: str, facts: Iterable[dict], hints: Hints | None = None) -> Applied:
    """Apply a gateway's facts in order, in one transaction; a fact that cannot be applied is
    logged, counted in ``rejected`` and skipped (the others still are).

    All facts are first applied in one go; only when one of them fails is the batch rolled back
    and applied again fact by fact, each in a savepoint of its own (the usual batch, a reply's
    two or three facts, costs no savepoint).

    The request path and the ingest process apply a reply's facts side by side. Should
    PostgreSQL still end one of them as a deadlock victim (or a serialization failure), the
    batch is applied again, up to CONFLICT_ATTEMPTS times; inside a caller's transaction (the
    ingest's) the caller does that, since the locks taken before would still be held."""
    facts = list(facts)
    attempts = 1 if transaction.get_connection().in_atomic_block else CONFLICT_ATTEMPTS
    attempt = 1
    while True:
        try:
            return _apply_batch(gateway, facts, hints)
        except OperationalError as exc:
            if attempt >= attempts or not _conflict(exc):
                raise
            attempt += 1
            log.warning("gateway %s: applying %d fact(s) again after a database conflict (%s)", gateway,
                        len(facts), str(exc).splitlines()[0])


def _apply_batch(gateway: str, facts: list, hints: Hints | None) -> Applied:
    try:
        return _apply_all(gateway, facts, hints, isolated=False)
    except (OperationalError, InterfaceError):
        raise  # the database itself is unavailable, or a conflict: the whole batch is tried again
    except Exception:  # noqa: BLE001 - some fact fails: find which, apply the others
        return _apply_all(gateway, facts, hints, isolated=True)


def _conflict(exc: OperationalError) -> bool:
    """Whether PostgreSQL ended the transaction for a conflict with another one, to be tried
    again: a deadlock (40P01) or a serialization failure (40001)."""
    return getattr(exc.__cause__, "sqlstate", None) in CONFLICT_STATES


def _apply_all(gateway: str, facts: list, hints: Hints | None, isolated: bool) -> Applied:
    applied = Applied()
    with transaction.atomic():
        known = KnownRecords(gateway, hints, isolated)
        known.prefetch(facts)
        for fact in facts:
            if not isolated:
                apply_fact(known, fact, applied)
                applied.accepted.append(fact)
                continue
            try:
                with transaction.atomic():  # a savepoint: a fact that fails, fails alone
                    apply_fact(known, fact, applied)
                applied.accepted.append(fact)
            except (OperationalError, InterfaceError):
                raise
            except Exception as exc:  # noqa: BLE001 - whatever a malformed fact causes, it must not block the rest
                applied.rejected += 1
                known.nodes.clear()  # what the failed fact created is gone
                kind = fact.get("type") if isinstance(fact, dict) else type(fact).__name__
                log.warning("gateway %s: skipped a %s fact that cannot be applied: %s: %s", gateway, kind,
                            type(exc).__name__, exc)
    return applied


def apply_fact(known: KnownRecords, fact: dict, applied: Applied) -> None:
    if not isinstance(fact, dict):
        raise FactRejected("a fact must be a JSON object")
    if fact.get("gateway") != known.name:
        raise FactRejected(f"it names gateway {fact.get('gateway')!r}, but came from {known.name}")
    kind = fact.get("type")
    handler = HANDLERS.get(kind)
    if handler is None:
        raise FactRejected(f"unknown fact type {kind!r}")
    handler(known, fact, checks.moment(fact.get("at"), "at"), applied)


def _node_seen(known: KnownRecords, fact: dict, at: datetime, applied: Applied) -> None:
    robot = known.robot(fact)
    name = checks.node_name(fact.get("node"))
    node = known.node(robot, name)
    if node is None:
        known.new_node(robot, name, at)
        return
    ManagedNode.objects.filter(pk=node.pk).update(alive=True, gone_reason="", last_seen=at,
                                                  first_seen=Coalesce("first_seen", at))
    node_back([node.pk], at)


def _node_gone(known: KnownRecords, fact: dict, at: datetime, applied: Applied) -> None:
    robot = known.robot(fact)
    node = known.node(robot, checks.node_name(fact.get("node")))
    if node is not None:
        reason = fact.get("reason") if fact.get("reason") in GONE_REASONS else ""
        ManagedNode.objects.filter(pk=node.pk).update(alive=False, gone_reason=reason, last_seen=at)
        node_left([node.pk], at, reason)
        if reason == protocol.PROCESS_LOST:
            _process_seen(node, "lost", checks.optional_moment(fact.get("since"), "since") or at)


def _process_seen(node: ManagedNode, status: str, at: datetime) -> None:
    """The node's process was lost or restarted at ``at`` (a later report is never overwritten
    by an earlier one applied late)."""
    ManagedNode.objects.filter(pk=node.pk).filter(Q(process_since__isnull=True) | Q(process_since__lte=at)).update(
        process_status=status, process_since=at
    )


def _node_state(known: KnownRecords, fact: dict, at: datetime, applied: Applied) -> None:
    robot = known.robot(fact)
    state_id = checks.state_id(fact.get("state_id"))
    name = checks.node_name(fact.get("node"))
    changes = {"state_id": state_id, "state_label": sm.state_label(state_id), "state_changed": at}
    node = known.node(robot, name)
    if node is None:
        chain = {"audited_state_id": state_id} if sm.is_primary(state_id) else {}
        known.new_node(robot, name, at, **changes, **chain)
        return
    # Applied twice or late (the request path and the ingest process both apply a reply's
    # facts), an older state never overwrites a newer one.
    ManagedNode.objects.filter(pk=node.pk).filter(Q(state_changed__isnull=True) | Q(state_changed__lte=at)).update(
        last_seen=at, **changes, **state_chain.seen_in(state_id)
    )


def _robot_nodes(known: KnownRecords, fact: dict, at: datetime, applied: Applied) -> None:
    robot = known.robot(fact)
    listed = fact.get("nodes")
    if not isinstance(listed, list) or len(listed) > ROBOT_NODES_LIMIT:
        raise FactRejected(f"nodes must be a list of at most {ROBOT_NODES_LIMIT} node names")
    listed = [checks.node_name(name) for name in listed]
    unlisted = ManagedNode.objects.filter(robot=robot).exclude(name__in=listed)
    node_left(unlisted.filter(alive=True).values_list("id", flat=True), at)
    unlisted.update(alive=False)
    present = ManagedNode.objects.filter(robot=robot, name__in=listed)
    node_back(present.values_list("id", flat=True), at)
    present.update(alive=True, gone_reason="", last_seen=at, first_seen=Coalesce("first_seen", at))
    known.load_robot(robot)
    for name in listed:  # a node.seen that was lost on the way
        if known.node(robot, name) is None:
            known.new_node(robot, name, at)


def _requester(known: KnownRecords, user_id: int | None) -> dict[str, Any]:
    """The audit record's requested_by fields for a user (none for a deleted user)."""
    if user_id is None:
        return {}
    name = known.username(user_id)
    return {} if name is None else {"requested_by_id": user_id, "requested_by_name": name}


def _transition_id(value: Any) -> int | None:
    if value is None:
        return None
    if not isinstance(value, int) or isinstance(value, bool) or value not in sm.TRANSITIONS_BY_ID:
        raise FactRejected(f"transition_id {str(value)[:20]!r} is not a lifecycle transition")
    return int(value)


def _run_id(value: Any) -> str:
    if value in (None, ""):
        return ""
    if not isinstance(value, str) or not checks.RUN_ID_RE.match(value):
        raise FactRejected("run_id must be up to 32 hexadecimal digits")
    return value


def _label(state_id: int | None) -> str:
    return "" if state_id is None else sm.state_label(state_id)


def _transition(known: KnownRecords, fact: dict, at: datetime, applied: Applied) -> None:
    fact_id = str(fact["id"])
    if fact_id in known.stored:
        applied.transitions[fact_id] = TransitionRecord.objects.select_related("node").get(fact_id=fact_id)
        return
    robot = known.robot(fact)
    name = checks.node_name(fact.get("node"))
    node = known.node(robot, name)
    transition_id = _transition_id(fact.get("transition_id"))
    start = checks.optional_state_id(fact.get("start_state"))
    result = checks.optional_state_id(fact.get("result_state"))
    goal = sm.SUCCESS_GOAL.get(transition_id) if transition_id is not None else None
    requested_at = checks.moment(fact.get("requested_at"), "requested_at")
    completed_at = checks.optional_moment(fact.get("completed_at"), "completed_at")
    outcome = checks.choice(fact.get("outcome"), TransitionRecord.Outcome.values, "outcome")
    source, user_id, claimed = attribution.requester(known, fact, robot)
    error = checks.text(fact.get("error")) + claimed
    if outcome == TransitionRecord.Outcome.OBSERVED and start is None and node is not None:
        start, error = state_chain.start_of_observed(node, result, requested_at)
    elif node is not None and (bridged := state_chain.bridge(node, start, requested_at)) is not None:
        applied.created.append(bridged)
    record = TransitionRecord(
        fact_id=fact_id,
        node=node,
        robot=robot,
        robot_name=robot.name,
        node_name=name,
        transition_id=transition_id,
        transition_label=checks.text(fact.get("transition_label"), checks.LABEL_LENGTH),
        start_state_id=start,
        start_state_label=_label(start),
        goal_state_id=goal,
        goal_state_label=_label(goal),
        result_state_id=result,
        result_state_label=_label(result),
        outcome=outcome,
        source=source,
        **_requester(known, user_id),
        requested_at=requested_at,
        completed_at=completed_at,
        duration_ms=round((completed_at - requested_at).total_seconds() * 1000, 2) if completed_at else None,
        error=error,
        run_id=_run_id(fact.get("run_id")),
    )
    if save_once(known, record):
        applied.created.append(record)
        if node is not None:
            state_chain.recorded(node, result, completed_at or requested_at)
        if node is not None and outcome in PROCESS_STATUS:
            _process_seen(node, PROCESS_STATUS[outcome], completed_at or requested_at)
    else:
        record = TransitionRecord.objects.select_related("node").get(fact_id=fact_id)
    applied.transitions[fact_id] = record


def _parameter(known: KnownRecords, fact: dict, at: datetime, applied: Applied) -> None:
    fact_id = str(fact["id"])
    if fact_id in known.stored:
        applied.parameters[fact_id] = ParameterRecord.objects.get(fact_id=fact_id)
        return
    robot = known.robot(fact)
    name = checks.node_name(fact.get("node"))
    outcome = checks.choice(fact.get("outcome"), ("succeeded", "rejected", "observed", "timed_out"), "outcome")
    source, user_id, claimed = attribution.requester(known, fact, robot)
    record = ParameterRecord(
        fact_id=fact_id,
        node=known.node(robot, name),
        robot_name=robot.name,
        node_name=name,
        name=checks.text(fact.get("name"), 255),
        old_value=checks.storable(checks.value(fact.get("old"))),
        new_value=checks.storable(checks.value(fact.get("new"))),
        outcome=outcome,
        reason=checks.text(fact.get("reason")) + claimed,
        source=source,
        **_requester(known, user_id),
        at=at,
        run_id=_run_id(fact.get("run_id")),
    )
    if save_once(known, record):
        applied.created_parameters.append(record)
    else:
        record = ParameterRecord.objects.get(fact_id=fact_id)
    applied.parameters[fact_id] = record


def _run(known: KnownRecords, fact: dict, at: datetime, applied: Applied) -> None:
    run_id = _run_id(fact.get("run_id"))
    if not run_id:
        raise FactRejected("a run fact needs its run_id")
    status = checks.choice(fact.get("status"), GroupRun.Status.values, "run status")
    changes: dict[str, Any] = {"status": status}
    if "message" in fact:
        changes["message"] = checks.text(fact["message"])
    if "results" in fact:
        changes["results"] = checks.run_results(fact["results"])
    for name in ("started", "finished"):
        if fact.get(name):
            changes[name] = checks.moment(fact[name], name)
    # The run's row only ("self"): locking its robot's row too would block, until this batch
    # commits, every audit record that refers to that robot (a foreign key check), and once
    # deadlocked the request path applying a reply's facts against the ingest process.
    run = GroupRun.objects.select_for_update(of=("self",)).select_related("robot").filter(pk=run_id).first()
    if run is None:
        # The one run a gateway starts on its own: the automatic recovery of the nodes of a
        # restarted process (no more than a run's results may hold).
        if fact.get("operation") != "recover" or fact.get("source", "recovery") != "recovery":
            raise FactRejected(f"there is no run {run_id}, and a gateway may start only recoveries")
        robot = known.robot(fact)
        only = fact.get("only_nodes") or []
        if not isinstance(only, list) or not 1 <= len(only) <= checks.RUN_RESULTS:
            raise FactRejected(f"a recovery is of 1 to {checks.RUN_RESULTS} nodes")
        timeout = fact.get("node_timeout")
        GroupRun.objects.create(
            id=run_id, robot=robot, operation="recover",
            only_nodes=list(dict.fromkeys(checks.node_name(name) for name in only)),
            source="recovery", policy=checks.choice(fact.get("policy") or "stop", GroupRun.Policy.values, "policy"),
            node_timeout=min(max(float(timeout), 0.1), 60.0) if isinstance(timeout, (int, float))
            and not isinstance(timeout, bool) and timeout == timeout else 5.0, **changes,
        )
        return
    if not known.owns(run.robot.name):
        raise FactRejected(f"run {run_id} is for robot {run.robot.name}, not one of gateway {known.name}'s")
    if run.status in GroupRun.ENDED:
        # A verdict is final (the site's or the gateway's own): a progress report that comes
        # after it is dropped, an end reported after it is kept as what it is, beside it.
        if status in GroupRun.ENDED:
            _late_end(run, status, changes)
        return
    GroupRun.objects.filter(pk=run_id).update(**changes)


LATE_END = "; after this verdict the gateway reported: "


def _late_end(run: GroupRun, status: str, changes: dict[str, Any]) -> None:
    """The gateway's end of a run the site had already ended: its status stays; the message
    says what the gateway reported, and the results are the gateway's (what its nodes did)."""
    said = str(changes.get("message") or "")
    if status == run.status and said == run.message:
        return  # the report that ended it, applied again
    verdict = run.message.split(LATE_END, 1)[0]
    message = f"{verdict}{LATE_END}{status}" + (f" ({said})" if said else "")
    late = {"message": message, **({"results": changes["results"]} if "results" in changes else {})}
    if message != run.message:
        GroupRun.objects.filter(pk=run.pk).update(**late)
        log.warning("run %s: the gateway reported it %s after it had ended %s; it stays %s", run.pk, status,
                    run.status, run.status)


def _gateway_started(known: KnownRecords, fact: dict, at: datetime, applied: Applied) -> None:
    message = (f"the gateway {known.name} restarted while it ran (instance {fact.get('instance', '?')}); "
               "its last results are kept")
    open_states = (GroupRun.Status.QUEUED, GroupRun.Status.RUNNING)
    ids = list(GroupRun.objects.filter(robot__gateway__name=known.name, status__in=open_states, created__lt=at)
               .values_list("id", flat=True))
    if ids:
        GroupRun.objects.filter(id__in=ids, status__in=open_states).update(
            status=GroupRun.Status.FAILED, message=message, finished=at)
        # The instance that ran them may only have been frozen while this one took its lease:
        # should it wake up, it stops at its next step.
        transaction.on_commit(lambda: verdicts.publish(known.name, ids, GroupRun.Status.FAILED, message, at))


HANDLERS = {
    protocol.NODE_SEEN: _node_seen,
    protocol.NODE_GONE: _node_gone,
    protocol.NODE_STATE: _node_state,
    protocol.ROBOT_NODES: _robot_nodes,
    protocol.TRANSITION: _transition,
    protocol.PARAMETER: _parameter,
    protocol.RUN: _run,
    protocol.GATEWAY_STARTED: _gateway_started,
    protocol.PROCESS: apply_process,
    protocol.NODE_PROCESS: apply_node_process,
    protocol.ENFORCEMENT_STOPPED: apply_enforcement_stopped,
    protocol.TOPIC_RATES: apply_topic_rates,
    protocol.DIAGNOSTICS: apply_diagnostics,
}
