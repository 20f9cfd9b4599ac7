"""ROS 2 parameter files (the YAML `ros2 param dump` writes and `--params-file` reads)."""
from __future__ import annotations

from typing import Any

import yaml
from django.utils.translation import gettext as _

from ros_gateway.shared import param_types as pt


class ParameterFileError(ValueError):
    """The file cannot be used; the message says why."""


# A ROS parameter file nests a few levels (the node, ros__parameters, namespaces, a flat array).
MAX_NESTING = 32
# ROS integers are 64-bit (at most 20 characters in decimal, 66 in binary). Making a Python
# int of a much longer literal is refused (ValueError beyond 4,300 digits) or slow (YAML 1.1's
# base 60, 1:2:3:…, is quadratic).
MAX_INTEGER_CHARS = 100


def _line(node_or_event: yaml.Node | yaml.Event) -> int | None:
    """The line it starts on, counted from 1 (None if not known)."""
    mark = node_or_event.start_mark
    return mark.line + 1 if mark is not None else None


def _bounded_int(loader: yaml.constructor.SafeConstructor, node: yaml.ScalarNode) -> int:
    if len(node.value) > MAX_INTEGER_CHARS:
        line = _line(node)
        if line is None:
            raise ParameterFileError(_("an integer of more than %(count)s characters; ROS integers are 64-bit") % {
                "count": MAX_INTEGER_CHARS})
        raise ParameterFileError(_("an integer of more than %(count)s characters (line %(line)s); ROS integers are "
                                   "64-bit") % {"count": MAX_INTEGER_CHARS, "line": line})
    return loader.construct_yaml_int(node)


def _too_deep(line: int | None) -> ParameterFileError:
    if line is None:
        return ParameterFileError(_("lists or mappings nested more than %(count)s levels deep; a parameter file "
                                    "needs only a few") % {"count": MAX_NESTING})
    return ParameterFileError(_("lists or mappings nested more than %(count)s levels deep (line %(line)s); a "
                                "parameter file needs only a few") % {"count": MAX_NESTING, "line": line})


class _PythonLoader(yaml.SafeLoader):
    """PyYAML's pure-Python safe loader, stopped at the nesting limit while scanning: its
    scanner reads ahead over every '[' or '{' that may start a key, in time quadratic in their
    depth (5,000 '[' took 9.5 s of CPU) before the parser sees the first of them."""

    def fetch_flow_collection_start(self, TokenClass: type) -> None:  # noqa: N803 (PyYAML's name)
        if self.flow_level >= MAX_NESTING:
            raise _too_deep(self.line + 1)
        super().fetch_flow_collection_start(TokenClass)


_PythonLoader.add_constructor("tag:yaml.org,2002:int", _bounded_int)

if yaml.__with_libyaml__:
    class _CLoader(yaml.CSafeLoader):
        """libyaml's parser (the wheels have it): hands events on as it reads, and parses a
        256 KiB file in a tenth of the time the Python one takes."""

    _CLoader.add_constructor("tag:yaml.org,2002:int", _bounded_int)
    LOADER: type = _CLoader
else:
    LOADER = _PythonLoader


def _check_events(text: str) -> None:
    """Refuse aliases and deep nesting from the event stream, before a document is built."""
    depth = 0
    for event in yaml.parse(text, Loader=LOADER):
        if isinstance(event, yaml.AliasEvent):
            # *name repeats a value: nested ones turn a few lines into gigabytes
            raise ParameterFileError(_("aliases (*name) are not supported in a parameter file; write the values out"))
        if isinstance(event, yaml.CollectionStartEvent):
            depth += 1
            if depth > MAX_NESTING:
                raise _too_deep(_line(event))
        elif isinstance(event, yaml.CollectionEndEvent):
            depth -= 1


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
        _check_events(text)
        document = yaml.load(text, Loader=LOADER)  # a safe loader (above)
    except yaml.YAMLError as exc:
        raise ParameterFileError(_("not valid YAML: %(error)s") % {"error": exc}) from None
    if not isinstance(document, dict) or not document:
        raise ParameterFileError(_("expected a mapping such as '/node: {ros__parameters: {...}}'"))
    bare = node_name.lstrip("/")
    for key in (node_name, bare, "/**", "**"):
        if key in document:
            section = document[key]
            break
    else:
        if len(document) != 1:
            found = ", ".join(map(str, document))
            raise ParameterFileError(_("the file has no section for %(node)s (found: %(found)s)") % {
                "node": node_name, "found": found})
        section = next(iter(document.values()))
    if not isinstance(section, dict) or not isinstance(section.get("ros__parameters"), dict):
        raise ParameterFileError(_("the node's section has no 'ros__parameters' mapping"))
    return _flatten(section["ros__parameters"])


def _not_finite_note(value: Any) -> str:
    """Why a value from a file cannot be set, if it is or holds .nan or .inf (YAML has both)."""
    found = pt.non_finite(value)
    if found is None:
        return ""
    path, number = found
    if path:  # ROS arrays are flat: the index says where
        return _("cannot be set: item %(index)s is %(number)s, not a finite number") % {
            "index": path[0], "number": number}
    return _("cannot be set: %(number)s, not a finite number") % {"number": number}


def diff(current: list[dict], wanted: dict[str, Any]) -> list[dict]:
    """What applying ``wanted`` would change: one entry per parameter that differs, with
    ``value``, the file's value as the parameter's type wants it (what is sent). An entry with a
    note is shown, not applied: the note says why, from every check the gateway makes before it
    sends a value (no such parameter, read-only, type, the descriptor's ranges:
    ``param_types.check``), and values no JSON can carry (.nan, .inf). The node may still refuse
    a value its own checks do not like: only it can say so."""
    by_name = {p["name"]: p for p in current}
    changes = []
    for name, value in sorted(wanted.items()):
        parameter = by_name.get(name)
        change = {"name": name, "old": None if parameter is None else parameter["value"], "new": value,
                  "value": value, "note": ""}
        if parameter is None:
            change["note"], change["missing"] = _("the node has no such parameter"), True
        elif note := _not_finite_note(value):
            change["note"] = note
        elif parameter["value"] == value:
            continue  # already so (a read-only one included)
        else:
            try:
                change["value"] = pt.check(value, parameter)
            except pt.InvalidValue as exc:
                change["note"] = str(exc)
        changes.append(change)
    return changes
