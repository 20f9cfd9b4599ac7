"""The audit log's chain of states: every state a node is seen in follows from the record before it.

A node's records (ingest.facts) each say which state they left it in. Some changes reach no
record: a gateway killed while a transition was under way (its request timed out, but the node
went on), a change by another tool while no gateway watched. The site notices: a node seen in
a primary state other than the one its records leave it in is "unexplained" from then on; a
record that ends in that state explains it (the gateway's transition record of the same change
arrives a moment after the state). One still unexplained after GRACE_S becomes a record of its
own: outcome ``observed``, from the state the records had to the state seen, with what is known
of its cause (the request or run that was under way). See docs/architecture.md.
"""
from __future__ import annotations

import hashlib
import logging
from datetime import datetime, timedelta

from django.db.models import Case, F, Q, Value, When
from django.db.models.functions import Coalesce
from django.utils import timezone, translation

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import GroupRun, ManagedNode
from ros_gateway.shared import state_machine as sm

log = logging.getLogger(__name__)

GRACE_S = 5.0
UNANSWERED_LOOKBACK = 20  # records without a result looked through for an unanswered request
RUN_CONTEXT = timedelta(minutes=10)  # a run that ended this long before still names the cause


def seen_in(state_id: int) -> dict:
    """The fields of a node's state update that keep its chain: a first state is where its chain
    may begin (``audited_at`` stays empty until a record says so); another primary state than
    its records' is unexplained from now (unless already so). Seeing the records' own state
    again does not clear the mark: the next request's reply shows its new state before its
    record, and that record may start where the node went unrecorded (bridge). A record
    ending in the state seen, or the settle, clears it; a node that leaves its records' state
    again is unexplained from then. (``state_id`` on the right is the row's state before this
    update, as SQL evaluates an UPDATE.)"""
    if not sm.is_primary(state_id):
        return {}
    now = Value(timezone.now())
    return {
        "audited_state_id": Coalesce(F("audited_state_id"), Value(state_id)),
        "unexplained_since": Case(
            When(audited_state_id__isnull=True, then=Value(None)),
            When(audited_state_id=state_id, then=F("unexplained_since")),
            When(Q(unexplained_since__isnull=True) | Q(state_id=F("audited_state_id")), then=now),
            default=F("unexplained_since"),
        ),
    }


def recorded(node: ManagedNode, result_state: int | None, at: datetime) -> None:
    """A record left the node in ``result_state`` at ``at`` (a later record is never overwritten
    by an earlier one applied late); it explains the node's state if that is the same."""
    if result_state is None or not sm.is_primary(result_state):
        return
    ManagedNode.objects.filter(pk=node.pk).filter(Q(audited_at__isnull=True) | Q(audited_at__lte=at)).update(
        audited_state_id=result_state, audited_at=at,
        unexplained_since=Case(When(state_id=result_state, then=Value(None)), default=F("unexplained_since")),
    )


def start_of_observed(node: ManagedNode, result: int | None, at: datetime) -> tuple[int | None, str]:
    """A gateway's own "observed" record (it saw only the end of a transition, e.g. just after
    it started): where the chain had the node, and what is known of the cause."""
    start = next(iter(ManagedNode.objects.filter(pk=node.pk).order_by().values_list("audited_state_id", flat=True)),
                 None)
    return start, cause(node, start, result if result is not None else node.state_id, at)


def bridge(node: ManagedNode, start: int | None, requested_at: datetime) -> TransitionRecord | None:
    """A record about to be stored starts where the node's records do not leave it, and the site
    has seen the node there, unexplained (the change in between reached no record, and the
    operator acted on the state seen before the sweep came): the change in between is recorded
    first, as ``observed``. Not when the site has not seen it: the record that explains it may
    still be on its way (the ingest behind the request path); unless a request after the last
    known result was left unanswered by a gateway whose process ended: none can come then."""
    if start is None or not sm.is_primary(start):
        return None
    found = next(iter(ManagedNode.objects.filter(pk=node.pk).order_by().values_list(
        "audited_state_id", "audited_at", "unexplained_since")), None)
    # (No record yet: the first state seen only marks where the chain may begin; the first
    # record says where it does. Its own result may even have been seen first.)
    if found is None or found[0] is None or found[1] is None or found[0] == start:
        return None
    audited, _, since = found
    if since is None:
        since = _unanswered_since(node, requested_at)
        if since is None:
            return None
    moment = min(since, requested_at - timedelta(microseconds=1))
    node.audited_state_id, node.unexplained_since = audited, moment
    record = observed(node, moment, found_state=start)
    ManagedNode.objects.filter(pk=node.pk).update(audited_state_id=start, audited_at=moment, unexplained_since=None)
    return record


def _unanswered_since(node: ManagedNode, before: datetime) -> datetime | None:
    """Just after the request left unanswered because its gateway's process ended (the site's own
    record: timed out, no result, no completion), if one came after the node's last known result:
    the node went on without a record, and none can come now (the site has not seen its new state
    yet when the next request's reply is stored before the new gateway's state fact)."""
    for record in TransitionRecord.objects.filter(node=node, requested_at__lt=before).order_by(
            "-requested_at", "-id")[:UNANSWERED_LOOKBACK]:
        if record.result_state_id is not None:
            return None
        if record.outcome == TransitionRecord.Outcome.TIMED_OUT and record.completed_at is None:
            return record.requested_at + timedelta(microseconds=1)
    return None


def settle(now: datetime | None = None) -> list[TransitionRecord]:
    """Records of the states still unexplained after GRACE_S (the ingest's leader, every few
    seconds; idempotent: a record's fact id comes from the node and the moment)."""
    now = now or timezone.now()
    made = []
    # (Not while its gateway's facts wait in Redis: the record that explains it may be among them.)
    due = ManagedNode.objects.select_related("robot").filter(
        unexplained_since__lte=now - timedelta(seconds=GRACE_S), robot__gateway__backlog=0)
    for node in due:
        if node.audited_state_id == node.state_id or not sm.is_primary(node.state_id):
            ManagedNode.objects.filter(pk=node.pk, unexplained_since=node.unexplained_since).update(
                unexplained_since=None)
            continue
        record = observed(node, now)
        made.append(record)
        ManagedNode.objects.filter(pk=node.pk, unexplained_since=node.unexplained_since).update(
            audited_state_id=node.state_id, audited_at=now, unexplained_since=None)
    return made


def observed(node: ManagedNode, now: datetime, found_state: int | None = None) -> TransitionRecord:
    start = node.audited_state_id
    found = node.state_id if found_state is None else found_state
    fact_id = hashlib.sha256(f"observed:{node.pk}:{node.unexplained_since.isoformat()}:{found}".encode()
                             ).hexdigest()[:32]
    existing = TransitionRecord.objects.filter(fact_id=fact_id).first()
    if existing is not None:
        return existing
    transition = next((t for t in sm.TRANSITIONS if t.external and t.start == start
                       and sm.SUCCESS_GOAL.get(t.id) == found), None)
    record = TransitionRecord.objects.create(
        fact_id=fact_id, node=node, robot=node.robot, robot_name=node.robot.name, node_name=node.name,
        transition_id=None, transition_label=transition.label if transition else "",
        start_state_id=start, start_state_label=sm.state_label(start) if start is not None else "",
        result_state_id=found, result_state_label=sm.state_label(found),
        outcome=TransitionRecord.Outcome.OBSERVED, source=TransitionRecord.Source.EXTERNAL,
        requested_at=node.unexplained_since, completed_at=None,
        error=cause(node, start, found, node.unexplained_since),
    )
    log.info("%s on %s: %s", node.name, node.robot.name, record.error)
    return record


def cause(node: ManagedNode, start: int | None, found: int, moment: datetime) -> str:
    """What the site knows of why the node changed without a record of it."""
    label = sm.state_label(found)
    moved = f"{sm.state_label(start)} -> {label}" if start is not None else label
    text = f"Found {label} on reading its state again ({moved}); the cause is not known"
    last = TransitionRecord.objects.filter(node=node).order_by("-requested_at", "-id").first()
    if last is not None and last.outcome in (TransitionRecord.Outcome.TIMED_OUT, TransitionRecord.Outcome.REJECTED) \
            and last.result_state_id is None:
        what = f"{last.transition_label} " if last.transition_label else ""
        by = f" by {last.requested_by_name}" if last.requested_by_name else ""
        with translation.override("en"):  # a stored record: in English, whatever the site's language
            outcome = str(last.get_outcome_display())
        text += f": after request #{last.pk} ({what}{outcome}{by}) was not answered"
    run = GroupRun.objects.filter(robot_id=node.robot_id, created__lte=moment,
                                  created__gte=moment - RUN_CONTEXT).select_related(
        "requested_by").order_by("-created").first()
    if run is not None and (not run.only_nodes or node.name in run.only_nodes) and \
            (not run.finished or run.finished >= moment - RUN_CONTEXT):
        by = f" by {run.requested_by.get_username()}" if run.requested_by else ""
        text += (f"; the {run.get_operation_display().lower()} run {run.pk[:8]}{by} was under way "
                 f"({run.status}{': ' + run.message if run.message else ''})")
    return text + "."
