"""The group runs a page shows (run panels: templates/dashboard/_run.html) and what a panel needs
beyond a gateway's push of a run: who started it, when, and in how many steps of the robot's
bring-up order (the words for its failure policy depend on it)."""
from __future__ import annotations

from datetime import datetime, timedelta, timezone

from django.core.cache import cache
from django.db.models import Q

from lifecycle_site.fleet.models import GroupRun, ManagedNode

# A page shows every open run of what it shows and the latest few that ended this recently; a
# node page only the latest run that includes its node.
RECENT_RUNS_S = 15 * 60
RUNS_PER_ROBOT = 3
RUNS_READ = 200  # at most this many rows read for one page
# Every open page's socket asks every few seconds: answers are kept this long in the process's
# memory, so fifty screens cost one read (as snapshots.GATEWAY_VIEWS_TTL_S).
KEEP_S = 1.0
META_KEEP_S = 300.0  # who started a run and when does not change

DONE_STATUSES = ("succeeded", "failed", "partial")
DONE_RANK = 1_000_000  # run_rank of a run that is over, with no results


def run_rank(run: dict) -> int:
    """How far a run has come: a page never replaces a panel with an older state of it (a push,
    the database and a request's answer can arrive in any order). At the same progress, a panel
    that says who and when (the database's) ranks above one that does not (a gateway's push)."""
    progress = (DONE_RANK if run.get("status") in DONE_STATUSES else 0) + 2 * len(run.get("results") or [])
    return progress + (1 if run.get("created") else 0)


def includes(run: GroupRun, node_name: str, seen: bool) -> bool:
    """Whether the run drives the node: named in it, or a whole-robot run that lists it (one that
    is still open: any node seen running, since a whole-robot run leaves out names never seen)."""
    if run.only_nodes:
        return node_name in run.only_nodes
    if any(r.get("node") == node_name for r in run.results or [] if isinstance(r, dict)):
        return True
    return seen and not run.done


def not_started(run: GroupRun) -> bool:
    """A run refused at its start (its gateway offline: nothing was sent; operations/runs.start_run):
    the page that asked showed the refusal, which it drops once the gateway is back; as a red
    "failed" panel it would stay, saying so, after the gateway is back and later runs went well."""
    return run.status == GroupRun.Status.FAILED and run.started is None and run.finished is None and not run.results


def recent_runs(robot_id: int | None = None, node_name: str | None = None) -> dict[str, list[dict]]:
    """Runs to show, newest first, per robot name: the open ones and the RUNS_PER_ROBOT latest
    that ended within RECENT_RUNS_S. With ``node_name`` (a node page): only the latest run of its
    robot that includes that node."""
    since = datetime.now(timezone.utc) - timedelta(seconds=RECENT_RUNS_S)
    open_states = (GroupRun.Status.QUEUED, GroupRun.Status.RUNNING)
    rows = GroupRun.objects.select_related("robot", "requested_by").filter(
        Q(created__gte=since) | Q(status__in=open_states)).order_by("-created")
    if robot_id is not None:
        rows = rows.filter(robot_id=robot_id)
    seen = node_name is not None and ManagedNode.objects.filter(
        robot_id=robot_id, name=node_name, last_seen__isnull=False).exists()
    by_robot: dict[str, list[dict]] = {}
    for run in rows[:RUNS_READ]:
        if not_started(run):
            continue
        if node_name is not None:
            if includes(run, node_name, seen):
                return {run.robot.name: [run.as_dict()]}
            continue
        shown = by_robot.setdefault(run.robot.name, [])
        if not run.done or sum(1 for r in shown if r["status"] not in open_states) < RUNS_PER_ROBOT:
            shown.append(run.as_dict())
    return by_robot


def runs_view(robot_id: int | None = None, node_name: str | None = None) -> list[dict]:
    """recent_runs() as one list, oldest first, for a page's socket (kept KEEP_S)."""
    def read() -> list[dict]:
        runs = [run for shown in recent_runs(robot_id, node_name).values() for run in shown]
        return sorted(runs, key=lambda run: run["created"])

    return cache.get_or_set(f"socket-runs:{robot_id}:{node_name}", read, KEEP_S)


META_FIELDS = ("created", "requested_by", "source", "nodes", "steps")


def completed(run: dict) -> dict:
    """A run as a panel shows it: a gateway's push (which says nothing of who started it, when,
    nor in how many steps) completed from the database, read once per run (kept META_KEEP_S:
    every open page gets every push)."""
    if "created" in run:
        return run
    meta = cache.get(f"run-meta:{run['id']}")
    if meta is None:
        row = GroupRun.objects.select_related("robot", "requested_by").filter(pk=run["id"]).first()
        if row is None:  # (a recovery's row may not be stored yet: asked again next time)
            return run
        found = row.as_dict()
        meta = {name: found[name] for name in META_FIELDS}
        cache.set(f"run-meta:{run['id']}", meta, META_KEEP_S)
    return {**meta, **run}
