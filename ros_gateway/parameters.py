"""A node's parameters through its standard parameter services, each call bounded."""
from __future__ import annotations

from typing import Any

from rcl_interfaces.msg import Parameter, ParameterValue
from rcl_interfaces.srv import (
    DescribeParameters,
    GetParameters,
    ListParameters,
    SetParameters,
    SetParametersAtomically,
)

from ros_gateway.domain import RosDomain, ServiceTimeout, ServiceUnavailable
from ros_gateway.lifecycle import NodeUnreachable
from ros_gateway.shared import param_types as pt

_FIELDS = {
    pt.BOOL: "bool_value",
    pt.INTEGER: "integer_value",
    pt.DOUBLE: "double_value",
    pt.STRING: "string_value",
    pt.BYTE_ARRAY: "byte_array_value",
    pt.BOOL_ARRAY: "bool_array_value",
    pt.INTEGER_ARRAY: "integer_array_value",
    pt.DOUBLE_ARRAY: "double_array_value",
    pt.STRING_ARRAY: "string_array_value",
}


def from_msg(value: ParameterValue) -> Any:
    """A ParameterValue as plain JSON data (None when not set)."""
    field = _FIELDS.get(value.type)
    if field is None:
        return None
    data = getattr(value, field)
    if value.type == pt.BYTE_ARRAY:
        return [b if isinstance(b, int) else ord(b) for b in data]
    if value.type in (pt.BOOL_ARRAY, pt.INTEGER_ARRAY, pt.DOUBLE_ARRAY, pt.STRING_ARRAY):
        return list(data)
    return data


def to_msg(value: Any, type_name: str) -> ParameterValue:
    type_id = pt.TYPE_IDS[type_name]
    message = ParameterValue(type=type_id)
    if type_id == pt.BYTE_ARRAY:
        setattr(message, _FIELDS[type_id], [bytes([b]) for b in value])
    elif type_id in _FIELDS:
        setattr(message, _FIELDS[type_id], value)
    return message


def type_of(value: Any) -> str:
    """The parameter type a JSON value would naturally have (for dynamically typed ones)."""
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, int):
        return "integer"
    if isinstance(value, float):
        return "double"
    if isinstance(value, str):
        return "string"
    if isinstance(value, list) and value:
        return type_of(value[0]) + "_array"
    raise pt.InvalidValue("cannot tell the type of this value")


class NoAnswer(NodeUnreachable):
    """The request was sent but not answered in time: the node may have carried it out."""


async def _call(domain: RosDomain, fqn: str, service: str, srv_type, request, timeout: float):
    try:
        return await domain.call(fqn, service, srv_type, request, timeout)
    except ServiceTimeout as exc:
        raise NoAnswer(str(exc)) from None
    except ServiceUnavailable as exc:
        raise NodeUnreachable(str(exc)) from None


async def list_parameters(domain: RosDomain, fqn: str, timeout: float) -> list[dict]:
    """Every parameter with its type, value and descriptor, sorted by name."""
    listed = await _call(domain, fqn, "list_parameters", ListParameters, ListParameters.Request(), timeout)
    names = sorted(listed.result.names)
    if not names:
        return []
    described = await _call(
        domain, fqn, "describe_parameters", DescribeParameters, DescribeParameters.Request(names=names), timeout
    )
    values = await _call(domain, fqn, "get_parameters", GetParameters, GetParameters.Request(names=names), timeout)
    parameters = []
    for name, descriptor, value in zip(names, described.descriptors, values.values, strict=False):
        type_id = value.type or descriptor.type
        parameters.append(
            {
                "name": name,
                "type": pt.TYPE_NAMES.get(type_id, "not set"),
                "value": from_msg(value),
                "description": descriptor.description,
                "additional_constraints": descriptor.additional_constraints,
                "read_only": bool(descriptor.read_only),
                "dynamic_typing": bool(descriptor.dynamic_typing),
                "integer_range": [
                    {"from_value": r.from_value, "to_value": r.to_value, "step": r.step}
                    for r in descriptor.integer_range
                ],
                "floating_point_range": [
                    {"from_value": r.from_value, "to_value": r.to_value, "step": r.step}
                    for r in descriptor.floating_point_range
                ],
            }
        )
    return parameters


async def set_parameters(domain: RosDomain, fqn: str, values: dict[str, tuple[Any, str]], timeout: float) -> list[dict]:
    """Set ``{name: (value, type name)}``; the node's own answer for each (it may refuse)."""
    names = list(values)
    request = SetParameters.Request(
        parameters=[Parameter(name=name, value=to_msg(*values[name])) for name in names]
    )
    response = await _call(domain, fqn, "set_parameters", SetParameters, request, timeout)
    return [
        {"name": name, "successful": bool(result.successful), "reason": result.reason}
        for name, result in zip(names, response.results, strict=False)
    ]


async def set_parameters_atomically(domain: RosDomain, fqn: str, values: dict[str, tuple[Any, str]],
                                    timeout: float) -> list[dict]:
    """Set ``{name: (value, type name)}`` all together or not at all (the node's
    set_parameters_atomically service): its one answer, given for each name."""
    request = SetParametersAtomically.Request(
        parameters=[Parameter(name=name, value=to_msg(*values[name])) for name in values]
    )
    response = await _call(domain, fqn, "set_parameters_atomically", SetParametersAtomically, request, timeout)
    result = response.result
    return [{"name": name, "successful": bool(result.successful), "reason": result.reason} for name in values]
