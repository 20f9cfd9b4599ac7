"""What a mode run asks of each node (the site sends it with the run): a target state or none
(left alone), and parameter values set before the node is activated. Checked here, bounded, as
everything the gateway is sent."""
from __future__ import annotations

from typing import Any

from ros_gateway.shared import state_machine as sm

MAX_PARAMETERS = 64  # per node and run
# Lower to higher: a mode first takes down (in reverse order) the nodes whose target is below.
RANK = {sm.UNCONFIGURED: 0, sm.INACTIVE: 1, sm.ACTIVE: 2}
SET_PARAMETERS = "set parameters"  # a run's step that is not a transition


class BadPlan(ValueError):
    """The plan cannot be carried out; the message says why."""


def parse(spec: dict, names: list[str]) -> tuple[dict[str, int | None], dict[str, dict[str, Any]]]:
    """(node -> target state id or None, node -> {parameter: value}) for every node of the run."""
    targets, parameters = spec.get("targets"), spec.get("parameters") or {}
    if not isinstance(targets, dict) or not isinstance(parameters, dict):
        raise BadPlan("A mode run needs its targets as {node: state or null} and its parameters as "
                      "{node: {name: value}}.")
    missing = [name for name in names if name not in targets]
    if missing:
        raise BadPlan(f"The mode names no target for {', '.join(missing[:5])}.")
    checked: dict[str, int | None] = {}
    for name in names:
        label = targets[name]
        if label is not None and label not in sm.DESIRED_STATES:
            raise BadPlan(f"{label!r} is not a state a mode can ask of {name}; use one of "
                          f"{', '.join(sm.DESIRED_STATES)} or null (left alone).")
        checked[name] = None if label is None else sm.DESIRED_STATES[label]
    values: dict[str, dict[str, Any]] = {}
    for name, given in parameters.items():
        if name not in checked:
            raise BadPlan(f"Parameters are given for {name}, which is not one of the run's nodes.")
        if not isinstance(given, dict) or len(given) > MAX_PARAMETERS or not all(isinstance(k, str) for k in given):
            raise BadPlan(f"The parameters of {name} must be at most {MAX_PARAMETERS} {{name: value}}.")
        if given:
            values[name] = dict(given)
    return checked, values


def goes(direction: str, state: int, target: int) -> bool:
    """Whether a node in ``state`` moves ``direction`` ("down" or "up") to reach ``target``."""
    if state not in RANK or target not in RANK:
        return direction == "up"  # out of finalized or a transition state: the up phase says it cannot
    return RANK[target] < RANK[state] if direction == "down" else RANK[target] > RANK[state]
