"""How a robot differs from its current mode, node by node: a node not running, in another state,
or with a parameter value other than the mode's (a change recorded since the mode was applied,
a value the mode's run did not set, or a new process of the node, whose values are its defaults
again until the mode is applied: parameter_values.py)."""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

from django.utils.translation import gettext as _

from lifecycle_site.fleet.models import ManagedNode, Robot
from lifecycle_site.modes import parameter_values, readiness
from lifecycle_site.modes.models import CurrentMode

# Drift is listed for at most this many nodes of a robot (a mode holds at most definitions.MAX_NODES).
MAX_LISTED = 500
UNKNOWN, NOT_SET = parameter_values.UNKNOWN, parameter_values.NOT_SET


@dataclass(frozen=True)
class Difference:
    node: str
    kind: str  # "absent", "state" or "parameter"
    want: Any
    have: Any
    parameter: str = ""
    node_id: str = ""

    def words(self) -> str:
        if self.kind == "absent":
            return _("%(node)s is not running (the mode wants it %(state)s)") % {"node": self.node, "state": self.want}
        if self.kind == "state":
            return _("%(node)s is %(have)s, the mode wants %(want)s") % {
                "node": self.node, "have": self.have, "want": self.want}
        have = _(self.have) if self.have in (NOT_SET, UNKNOWN) else self.have
        return _("%(node)s: %(parameter)s is %(have)s, the mode sets %(want)s") % {
            "node": self.node, "parameter": self.parameter, "have": repr(have), "want": repr(self.want)}


def current(robot: Robot) -> CurrentMode | None:
    return CurrentMode.objects.select_related("mode", "applied_by", "run").filter(robot=robot).first()


def differences(robot: Robot, now_mode: CurrentMode | None = None) -> list[Difference]:
    now_mode = now_mode or current(robot)
    if now_mode is None:
        return []
    mode = now_mode.mode
    found: list[Difference] = []
    nodes = {n.name: n for n in ManagedNode.objects.filter(robot=robot, name__in=list(mode.nodes))}
    for name, entry in list(mode.nodes.items())[:MAX_LISTED]:
        node, want = nodes.get(name), entry.get("state")
        key = node.key if node else ""
        if want and (node is None or not node.alive):
            found.append(Difference(name, "absent", want, None, node_id=key))
            continue
        if want and node.state_label != want:
            found.append(Difference(name, "state", want, node.state_label, node_id=key))
        wanted = entry.get("parameters") or {}
        if not wanted or node is None:
            continue
        found.extend(Difference(name, "parameter", wanted[p], value, parameter=p, node_id=key)
                     for p, value in parameter_values.known(now_mode, node, list(wanted)).items() if value != wanted[p])
    return found


def summary(robot: Robot) -> dict:
    """The robot's mode and drift, as the API and the pages show it."""
    now_mode = current(robot)
    if now_mode is None:
        return {"mode": None, "drift": []}
    found = differences(robot, now_mode)
    return {"mode": now_mode.mode.name, "since": now_mode.since.isoformat(),
            "applied_by": now_mode.applied_by.get_username() if now_mode.applied_by else None,
            "run": now_mode.run_id, "in_mode": not found,
            "drift": [{**asdict(d), "message": d.words()} for d in found], **readiness.evaluate(now_mode)}
