"""ROS 2 parameter files (the YAML `ros2 param dump` writes and `--params-file` reads)."""
from __future__ import annotations

from typing import Any

import yaml

from ros_gateway.shared import param_types as pt


class ParameterFileError(ValueError):
    """The file cannot be used; the message says why."""


def dump(node_name: str, parameters: list[dict]) -> str:
    """``{node: {ros__parameters: {...}}}``, nested by the dots in parameter names."""
    tree: dict[str, Any] = {}
    for parameter in parameters:
        if parameter["value"] is None:
            continue
        *parents, leaf = parameter["name"].split(".")
        branch = tree
        for part in parents:
            branch = branch.setdefault(part, {})
        branch[leaf] = parameter["value"]
    return yaml.safe_dump({node_name: {"ros__parameters": tree}}, sort_keys=True, default_flow_style=False)


def _flatten(tree: dict, prefix: str = "") -> dict[str, Any]:
    flat = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            flat.update(_flatten(value, name + "."))
        else:
            flat[name] = value
    return flat


def load(text: str, node_name: str) -> dict[str, Any]:
    """The values a file gives this node: its own section, else a ``/**`` section, else the
    only section there is. Raises ParameterFileError with a readable reason."""
    try:
        if any(isinstance(event, yaml.AliasEvent) for event in yaml.parse(text, Loader=yaml.SafeLoader)):
            # *name repeats a value: nested ones turn a few lines into gigabytes
            raise ParameterFileError("aliases (*name) are not supported in a parameter file; write the values out")
        document = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ParameterFileError(f"not valid YAML: {exc}") from None
    except RecursionError:
        raise ParameterFileError("not valid YAML: lists or mappings nested too deeply") from None
    if not isinstance(document, dict) or not document:
        raise ParameterFileError("expected a mapping such as '/node: {ros__parameters: {...}}'")
    bare = node_name.lstrip("/")
    for key in (node_name, bare, "/**", "**"):
        if key in document:
            section = document[key]
            break
    else:
        if len(document) != 1:
            found = ", ".join(map(str, document))
            raise ParameterFileError(f"the file has no section for {node_name} (found: {found})")
        section = next(iter(document.values()))
    if not isinstance(section, dict) or not isinstance(section.get("ros__parameters"), dict):
        raise ParameterFileError("the node's section has no 'ros__parameters' mapping")
    return _flatten(section["ros__parameters"])


def _not_finite_note(value: Any) -> str:
    """Why a value from a file cannot be set, if it is or holds .nan or .inf (YAML has both)."""
    found = pt.non_finite(value)
    if found is None:
        return ""
    path, number = found
    where = f"item {path[0]} is " if path else ""  # ROS arrays are flat: the index says where
    return f"cannot be set: {where}{number}, not a finite number"


def diff(current: list[dict], wanted: dict[str, Any]) -> list[dict]:
    """What applying ``wanted`` would change: one entry per parameter that differs. An entry
    with a note (no such parameter, read-only, not a finite number) is shown, not applied."""
    by_name = {p["name"]: p for p in current}
    changes = []
    for name, value in sorted(wanted.items()):
        parameter = by_name.get(name)
        if parameter is None:
            changes.append({"name": name, "old": None, "new": value, "note": "the node has no such parameter"})
        elif note := _not_finite_note(value):
            changes.append({"name": name, "old": parameter["value"], "new": value, "note": note})
        elif parameter["value"] != value:
            note = "read-only" if parameter.get("read_only") else ""
            changes.append({"name": name, "old": parameter["value"], "new": value, "note": note})
    return changes
