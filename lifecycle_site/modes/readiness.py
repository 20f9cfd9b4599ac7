"""Whether a robot is ready in its current mode: every predicate of the mode holds (a node in a
state, a parameter equal to a value or within a range, a topic published at least N times a second
as the gateway measures it). Not ready since when is kept on the robot's CurrentMode ("not ready
for N s" is an alert rule kind). Parameters are known as drift.py knows them (parameter_values.py)."""
from __future__ import annotations

from dataclasses import asdict, dataclass
from datetime import timedelta

from django.utils import timezone
from django.utils.translation import gettext as _

from lifecycle_site.fleet.models import ManagedNode
from lifecycle_site.modes import parameter_values
from lifecycle_site.modes.models import CurrentMode, TopicRate

STALE_RATE_S = 10.0  # a rate older than this is not known any more (its gateway silent)


@dataclass(frozen=True)
class Check:
    words: str  # "/scan at >= 5 Hz over 5 s"
    holds: bool
    now: str  # what it is: "2.1 Hz", "inactive", "unknown"


def checks(now_mode: CurrentMode) -> list[Check]:
    robot, predicates = now_mode.robot, [p for p in now_mode.mode.ready_when if isinstance(p, dict)]
    names = {p["node"] for p in predicates if "node" in p}
    nodes = {n.name: n for n in ManagedNode.objects.filter(robot=robot, name__in=names)}
    wanted = {}
    for p in predicates:
        if "parameter" in p:
            wanted.setdefault(p["node"], set()).add(p["parameter"])
    values = {name: parameter_values.known(now_mode, nodes[name], sorted(params)) if name in nodes else {}
              for name, params in wanted.items()}
    fresh = timezone.now() - timedelta(seconds=STALE_RATE_S)
    rates = {r.topic: r for r in TopicRate.objects.filter(robot=robot, topic__in=[p.get("topic") for p in predicates])}
    found = []
    for p in predicates:
        if "topic" in p:
            rate = rates.get(p["topic"])
            hz = rate.hz if rate is not None and rate.at >= fresh else None
            now = _("no publisher") if rate is not None and rate.at >= fresh and hz is None else (
                _("not measured yet") if hz is None else f"{hz:g} Hz")
            words = _("%(topic)s at >= %(min_hz)s Hz over %(window)s s") % {
                "topic": p["topic"], "min_hz": f"{p['min_hz']:g}", "window": f"{p.get('window_s', 5.0):g}"}
            found.append(Check(words, hz is not None and hz >= p["min_hz"], now))
            continue
        node = nodes.get(p["node"])
        if "state" in p:
            running = node is not None and node.alive
            found.append(Check(f"{p['node']} {p['state']}", running and node.state_label == p["state"],
                               node.state_label if running else _("not running")))
            continue
        value = values.get(p["node"], {}).get(p["parameter"], parameter_values.NOT_SET)
        if "equals" in p:
            words, holds = f"{p['node']} {p['parameter']} = {p['equals']!r}", value == p["equals"]
        else:
            low, high = p.get("min", float("-inf")), p.get("max", float("inf"))
            words = _("%(node)s %(parameter)s within %(min)s..%(max)s") % {
                "node": p["node"], "parameter": p["parameter"], "min": p.get("min", "-"), "max": p.get("max", "-")}
            holds = isinstance(value, (int, float)) and not isinstance(value, bool) and low <= value <= high
        unknown = value in (parameter_values.NOT_SET, parameter_values.UNKNOWN)
        found.append(Check(words, holds and not unknown, _("unknown") if unknown else repr(value)))
    return found


def evaluate(now_mode: CurrentMode) -> dict:
    """{"ready", "not_ready_since", "readiness": [checks]}; keeps not_ready_since on the row."""
    found = checks(now_mode)
    ready = all(c.holds for c in found)
    since = now_mode.not_ready_since
    if ready and since is not None:
        since = None
        CurrentMode.objects.filter(pk=now_mode.pk).update(not_ready_since=None)
    elif not ready and since is None:
        since = timezone.now()
        CurrentMode.objects.filter(pk=now_mode.pk, not_ready_since__isnull=True).update(not_ready_since=since)
    now_mode.not_ready_since = since
    return {"ready": ready, "not_ready_since": since.isoformat() if since else None,
            "readiness": [asdict(c) for c in found]}
