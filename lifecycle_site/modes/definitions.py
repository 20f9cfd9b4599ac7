"""What a mode may say of a node, checked before it is stored: a fully qualified node name, a
target state the lifecycle can be driven to (or none) and parameter values of ROS 2's types."""
from __future__ import annotations

import re
from typing import Any

from django.core.exceptions import ValidationError

from ros_gateway.shared import param_types as pt
from ros_gateway.shared import state_machine as sm

MAX_NODES, MAX_PARAMETERS, MAX_TEXT, MAX_ITEMS = 500, 64, 4096, 1024
NODE_NAME = TOPIC_NAME = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")
MODE_NAME = re.compile(r"^[a-z0-9][a-z0-9_-]{0,62}$")
PARAMETER_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_.]{0,254}$")
STATES = tuple(sm.DESIRED_STATES)  # unconfigured, inactive, active
KEYS = {"state", "parameters"}


def _value_problem(value: Any) -> str:
    """Why the value is not one a ROS 2 parameter can take ("" if it is)."""
    if isinstance(value, (bool, int, str)) or (isinstance(value, float) and pt.non_finite(value) is None):
        return "text over 4096 characters" if isinstance(value, str) and len(value) > MAX_TEXT else ""
    if isinstance(value, list) and len(value) <= MAX_ITEMS:
        kinds = {bool if isinstance(v, bool) else (float if isinstance(v, (int, float)) else type(v)) for v in value}
        if len(kinds) <= 1 and kinds <= {bool, float, str} and all(not _value_problem(v) for v in value):
            return ""
        return "a list must hold values of one kind (true/false, numbers or texts)"
    return "not a number, true/false, text or list of one of these"


def problems(nodes: Any) -> list[str]:
    """Every problem of a mode's node table, in words; [] if it can be stored."""
    if not isinstance(nodes, dict):
        return ['The nodes must be a table {"/node": {"state": ..., "parameters": {...}}}.']
    if len(nodes) > MAX_NODES:
        return [f"A mode holds at most {MAX_NODES} nodes."]
    found: list[str] = []
    for name, entry in nodes.items():
        if not NODE_NAME.match(name):
            found.append(f"{name!r} is not a fully qualified node name (such as /lidar_driver).")
            continue
        if not isinstance(entry, dict) or set(entry) - KEYS:
            found.append(f"{name}: give only state and parameters.")
            continue
        state = entry.get("state")
        if state is not None and state not in STATES:
            found.append(f"{name}: {state!r} is not a state a mode can ask for; use {', '.join(STATES)} "
                         "or null (left alone).")
        parameters = entry.get("parameters") or {}
        if not isinstance(parameters, dict) or len(parameters) > MAX_PARAMETERS:
            found.append(f"{name}: parameters must be at most {MAX_PARAMETERS} {{name: value}}.")
            continue
        for key, value in parameters.items():
            if not PARAMETER_NAME.match(key):
                found.append(f"{name}: {key!r} is not a parameter name.")
            elif problem := _value_problem(value):
                found.append(f"{name}: {key} is {problem}.")
    return found


def _refuse(found: list[str]) -> None:
    if found:
        raise ValidationError(found)


def validate_nodes(nodes: Any) -> None:
    _refuse(problems(nodes))


MAX_PREDICATES = 32
PREDICATE_FORMS = ('{"node": "/lidar", "state": "active"}', '{"node": "/lidar", "parameter": "rate", "equals": 8.0}',
                   '{"node": "/lidar", "parameter": "rate", "min": 5, "max": 20}',
                   '{"topic": "/scan", "min_hz": 5, "window_s": 5}')


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and pt.non_finite(value) is None


def readiness_problems(predicates: Any) -> list[str]:
    """Every problem of a mode's readiness predicates, in words; [] if they can be stored."""
    if not isinstance(predicates, list) or len(predicates) > MAX_PREDICATES:
        return [f"Readiness is a list of at most {MAX_PREDICATES} predicates such as {PREDICATE_FORMS[0]}."]
    found = []
    for index, given in enumerate(predicates, 1):
        keys = set(given) if isinstance(given, dict) else set()
        if keys == {"node", "state"} and NODE_NAME.match(str(given["node"])) \
                and given["state"] in sm.STATE_LABELS.values():
            continue
        if {"node", "parameter"} <= keys and NODE_NAME.match(str(given["node"])) \
                and PARAMETER_NAME.match(str(given["parameter"])):
            rest = keys - {"node", "parameter"}
            if rest == {"equals"} and not _value_problem(given["equals"]):
                continue
            if rest and rest <= {"min", "max"} and all(_number(given[k]) for k in rest):
                continue
        if keys <= {"topic", "min_hz", "window_s"} and {"topic", "min_hz"} <= keys \
                and TOPIC_NAME.match(str(given["topic"])) and _number(given["min_hz"]) and given["min_hz"] >= 0 \
                and _number(given.get("window_s", 5.0)) and 0.5 <= given.get("window_s", 5.0) <= 60:
            continue
        found.append(f"Predicate {index} is not one of: {'; '.join(PREDICATE_FORMS)} (window_s 0.5 to 60 s).")
    return found


def validate_readiness(predicates: Any) -> None:
    _refuse(readiness_problems(predicates))

