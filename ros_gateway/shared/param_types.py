"""ROS 2 parameter types and the checks made before a value is sent. No rclpy: the site
validates with it too (rcl_interfaces/msg/ParameterType, ParameterDescriptor)."""
from __future__ import annotations

import math
from typing import Any

NOT_SET, BOOL, INTEGER, DOUBLE, STRING = 0, 1, 2, 3, 4
BYTE_ARRAY, BOOL_ARRAY, INTEGER_ARRAY, DOUBLE_ARRAY, STRING_ARRAY = 5, 6, 7, 8, 9

TYPE_NAMES = {
    NOT_SET: "not set",
    BOOL: "bool",
    INTEGER: "integer",
    DOUBLE: "double",
    STRING: "string",
    BYTE_ARRAY: "byte_array",
    BOOL_ARRAY: "bool_array",
    INTEGER_ARRAY: "integer_array",
    DOUBLE_ARRAY: "double_array",
    STRING_ARRAY: "string_array",
}
TYPE_IDS = {name: type_id for type_id, name in TYPE_NAMES.items()}


class InvalidValue(ValueError):
    """The value does not fit the parameter; the message says why, for the operator."""


def non_finite(value: Any, path: tuple = ()) -> tuple[tuple, float] | None:
    """The first NaN or infinite float in ``value`` (looking into lists and dicts) and where
    it is (keys and indexes), or None. Such a value has no JSON form, so it can neither be
    sent on nor stored in a JSON column."""
    if isinstance(value, float) and not math.isfinite(value):
        return path, value
    items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for key, item in items:
        found = non_finite(item, (*path, key))
        if found is not None:
            return found
    return None


def path_text(path: tuple) -> str:
    """Where a value is, as an engineer would write it: ``gains[2]``, ``limits.max``."""
    text = ""
    for key in path:
        text += f"[{key}]" if isinstance(key, int) else f".{key}" if text else str(key)
    return text


def storable(value: Any) -> Any:
    """``value`` with every NaN or infinite float as its text ("nan", "inf", "-inf"), so an
    audit record of any value is valid JSON."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, list):
        return [storable(item) for item in value]
    if isinstance(value, dict):
        return {key: storable(item) for key, item in value.items()}
    return value


INT64_MIN, INT64_MAX = -(2**63), 2**63 - 1  # ROS integer parameters are int64


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def is_number(value: Any) -> bool:
    """A finite int or float, not a bool (JSON numbers of any size included)."""
    # math.isfinite() of an int beyond a double's range raises; every int is finite.
    return _is_int(value) or isinstance(value, float) and math.isfinite(value)


def coerce(value: Any, type_name: str) -> Any:
    """``value`` as the parameter type wants it (an int is fine for a double), or InvalidValue."""
    if type_name == "bool":
        if isinstance(value, bool):
            return value
        raise InvalidValue("must be true or false")
    if type_name == "integer":
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        if not _is_int(value):
            raise InvalidValue("must be a whole number")
        if not INT64_MIN <= value <= INT64_MAX:
            raise InvalidValue(f"must be between {INT64_MIN} and {INT64_MAX} (a 64-bit integer)")
        return value
    if type_name == "double":
        if is_number(value):
            try:
                return float(value)
            except OverflowError:  # a whole number too large for a double
                raise InvalidValue("is too large for a double (about 1.8e308 at most)") from None
        raise InvalidValue("must be a number")
    if type_name == "string":
        if isinstance(value, str):
            return value
        raise InvalidValue("must be text")
    if type_name.endswith("_array"):
        if not isinstance(value, list):
            raise InvalidValue("must be a list")
        item_type = {"byte_array": "integer", "bool_array": "bool", "integer_array": "integer",
                     "double_array": "double", "string_array": "string"}[type_name]
        items = []
        for index, item in enumerate(value):
            try:
                items.append(coerce(item, item_type))
            except InvalidValue as exc:
                raise InvalidValue(f"item {index} {exc}") from None
        if type_name == "byte_array" and any(not 0 <= b <= 255 for b in items):
            raise InvalidValue("items must be bytes (0-255)")
        return items
    raise InvalidValue(f"has type {type_name!r}, which cannot be set")


def _in_range(value: float, low: float, high: float, step: float) -> bool:
    if not low <= value <= high:
        return False
    if not step:
        return True
    if value == high:
        return True  # ROS accepts the upper bound even off the step grid
    steps = (value - low) / step
    return math.isclose(steps, round(steps), abs_tol=1e-9)


def check(value: Any, descriptor: dict) -> Any:
    """Check one new value against the parameter's descriptor (as listed by the gateway).

    Returns the value coerced to the parameter's type; raises InvalidValue with the reason.
    """
    if descriptor.get("read_only"):
        raise InvalidValue("is read-only")
    type_name = descriptor.get("type", "not set")
    if type_name == "not set" or descriptor.get("dynamic_typing"):
        return value
    value = coerce(value, type_name)
    for bound in descriptor.get("integer_range") or []:
        if not _in_range(value, bound["from_value"], bound["to_value"], bound.get("step", 0)):
            raise InvalidValue(_range_text(bound))
    for bound in descriptor.get("floating_point_range") or []:
        if not _in_range(value, bound["from_value"], bound["to_value"], bound.get("step", 0.0)):
            raise InvalidValue(_range_text(bound))
    return value


def _range_text(bound: dict) -> str:
    text = f"must be between {bound['from_value']:g} and {bound['to_value']:g}"
    if bound.get("step"):
        text += f" in steps of {bound['step']:g}"
    return text
