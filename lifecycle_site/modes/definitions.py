"""What a mode may say of a node, checked before it is stored: a fully qualified node name, a
target state the lifecycle can be driven to (or none) and parameter values of ROS 2's types."""
from __future__ import annotations

import re
from typing import Any

from django.core.exceptions import ValidationError
from django.utils.translation import gettext as _
from django.utils.translation import gettext_lazy

from ros_gateway.shared import param_types as pt
from ros_gateway.shared import state_machine as sm

MAX_NODES, MAX_PARAMETERS, MAX_TEXT, MAX_ITEMS = 500, 64, 4096, 1024
NODE_NAME = TOPIC_NAME = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")
MODE_NAME = re.compile(r"^[a-z0-9][a-z0-9_-]{0,62}$")
PARAMETER_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_.]{0,254}$")
STATES = tuple(sm.DESIRED_STATES)  # unconfigured, inactive, active
KEYS = {"state", "parameters"}
TOO_LONG = "text over 4096 characters"
MIXED_LIST = "a list must hold values of one kind (true/false, numbers or texts)"
NOT_A_VALUE = "not a number, true/false, text or list of one of these"
# What problems() says of a parameter's value, by _value_problem()'s answer (one sentence each).
VALUE_PROBLEMS = {
    TOO_LONG: gettext_lazy("%(node)s: %(parameter)s is text over 4096 characters."),
    MIXED_LIST: gettext_lazy("%(node)s: %(parameter)s is a list must hold values of one kind (true/false, numbers "
                             "or texts)."),
    NOT_A_VALUE: gettext_lazy("%(node)s: %(parameter)s is not a number, true/false, text or list of one of these."),
}


def _value_problem(value: Any) -> str:
    """Why the value is not one a ROS 2 parameter can take ("" if it is): TOO_LONG, MIXED_LIST or
    NOT_A_VALUE (problems() says it in words, VALUE_PROBLEMS)."""
    if isinstance(value, (bool, int, str)) or (isinstance(value, float) and pt.non_finite(value) is None):
        return TOO_LONG if isinstance(value, str) and len(value) > MAX_TEXT else ""
    if isinstance(value, list) and len(value) <= MAX_ITEMS:
        kinds = {bool if isinstance(v, bool) else (float if isinstance(v, (int, float)) else type(v)) for v in value}
        if len(kinds) <= 1 and kinds <= {bool, float, str} and all(not _value_problem(v) for v in value):
            return ""
        return MIXED_LIST
    return NOT_A_VALUE


def problems(nodes: Any) -> list[str]:
    """Every problem of a mode's node table, in words; [] if it can be stored."""
    if not isinstance(nodes, dict):
        return [_('The nodes must be a table {"/node": {"state": ..., "parameters": {...}}}.')]
    if len(nodes) > MAX_NODES:
        return [_("A mode holds at most %(count)s nodes.") % {"count": MAX_NODES}]
    found: list[str] = []
    for name, entry in nodes.items():
        if not NODE_NAME.match(name):
            found.append(_("%(name)s is not a fully qualified node name (such as /lidar_driver).") % {
                "name": repr(name)})
            continue
        if not isinstance(entry, dict) or set(entry) - KEYS:
            found.append(_("%(node)s: give only state and parameters.") % {"node": name})
            continue
        state = entry.get("state")
        if state is not None and state not in STATES:
            found.append(_("%(node)s: %(state)s is not a state a mode can ask for; use %(states)s or null (left "
                           "alone).") % {"node": name, "state": repr(state), "states": ", ".join(STATES)})
        parameters = entry.get("parameters") or {}
        if not isinstance(parameters, dict) or len(parameters) > MAX_PARAMETERS:
            found.append(_("%(node)s: parameters must be at most %(count)s {name: value}.") % {
                "node": name, "count": MAX_PARAMETERS})
            continue
        for key, value in parameters.items():
            if not PARAMETER_NAME.match(key):
                found.append(_("%(node)s: %(parameter)s is not a parameter name.") % {
                    "node": name, "parameter": repr(key)})
            elif problem := _value_problem(value):
                found.append(VALUE_PROBLEMS[problem] % {"node": name, "parameter": key})
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
        return [_("Readiness is a list of at most %(count)s predicates such as %(example)s.") % {
            "count": MAX_PREDICATES, "example": PREDICATE_FORMS[0]}]
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
        found.append(_("Predicate %(index)s is not one of: %(forms)s (window_s 0.5 to 60 s).") % {
            "index": index, "forms": "; ".join(PREDICATE_FORMS)})
    return found


def validate_readiness(predicates: Any) -> None:
    _refuse(readiness_problems(predicates))

