"""Modes as YAML: exported and imported in the product's own form, and imported from a
system_modes model file (micro-ROS/system_modes: its systems' modes, their parts' target states
"active.MODE", and each node's parameters per mode), each shown as what it becomes before it is
saved. Bounded: the file's size, the modes and nodes it may make (definitions.py checks each)."""
from __future__ import annotations

import re
from typing import Any

import yaml
from django.utils.translation import gettext as _

from lifecycle_site.modes import definitions

MAX_BYTES = 256 * 1024
MAX_MODES = 100
MAX_DEPTH = 8  # systems within systems
DEFAULT = "__DEFAULT__"
SLUG = re.compile(r"[^a-z0-9_-]+")


class FileRefused(ValueError):
    """The file cannot be read as modes; the message says why."""


def export(modes: list[dict]) -> str:
    """``modes``: Mode.as_dict() of each."""
    body = {"modes": [{"name": m["name"], "description": m["description"], "nodes": m["nodes"],
                       **({"ready_when": m["ready_when"]} if m.get("ready_when") else {})} for m in modes]}
    return yaml.safe_dump(body, sort_keys=False, allow_unicode=True)


def read(text: str) -> tuple[list[dict], list[str]]:
    """The modes a file describes (name, description, nodes) and every problem found, in words."""
    if len(text.encode("utf-8", "surrogatepass")) > MAX_BYTES:
        raise FileRefused(_("The file is over %(size)s KB.") % {"size": MAX_BYTES // 1024})
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        where = getattr(exc, "problem_mark", None)
        problem = getattr(exc, "problem", None) or exc
        if where:
            raise FileRefused(_("The file is not YAML (line %(line)s): %(problem)s.") % {
                "line": where.line + 1, "problem": problem}) from None
        raise FileRefused(_("The file is not YAML: %(problem)s.") % {"problem": problem}) from None
    if isinstance(data, dict) and isinstance(data.get("modes"), list):
        modes, problems = _own(data["modes"]), []
    elif isinstance(data, dict) and any(_entry_type(v) for v in data.values()):
        modes, problems = _system_modes(data)
    else:
        raise FileRefused(_("The file holds no modes: expected 'modes:' (this product's export) or a system_modes "
                            "model file (entries with ros__parameters: type: system or node)."))
    if len(modes) > MAX_MODES:
        raise FileRefused(_("The file makes %(count)s modes; at most %(max)s are taken at once.") % {
            "count": len(modes), "max": MAX_MODES})
    for mode in modes:
        problems += [f"{mode['name']}: {p}" for p in definitions.problems(mode["nodes"])
                     + definitions.readiness_problems(mode.setdefault("ready_when", []))]
        if not definitions.MODE_NAME.match(mode["name"]):
            problems.append(_("%(name)s cannot be a mode's name (lower-case letters, digits, '-', '_').") % {
                "name": repr(mode["name"])})
    return modes, problems


def _own(entries: list) -> list[dict]:
    modes = []
    for entry in entries:
        if not isinstance(entry, dict):
            raise FileRefused(_("Each entry under 'modes:' must be a table with name and nodes."))
        modes.append({"name": str(entry.get("name") or ""), "description": str(entry.get("description") or ""),
                      "nodes": entry.get("nodes") if isinstance(entry.get("nodes"), dict) else {},
                      "ready_when": entry.get("ready_when") or []})
    return modes


def _entry_type(value: Any) -> str:
    params = value.get("ros__parameters") if isinstance(value, dict) else None
    kind = params.get("type") if isinstance(params, dict) else None
    return kind if kind in ("system", "node") else ""


def _parts(params: dict) -> list[str]:
    parts = params.get("parts")
    if isinstance(parts, str):
        return parts.split()
    return [str(p) for p in parts] if isinstance(parts, list) else []


def _node_name(name: str) -> str:
    return name if name.startswith("/") else f"/{name}"


def _mode_name(system: str, mode: str) -> str:
    return SLUG.sub("-", f"{system}-{mode.strip('_').lower() or 'default'}".lower()).strip("-")[:63]


def _system_modes(data: dict) -> tuple[list[dict], list[str]]:
    """Each mode of each top-level system (one that is no other system's part) as one mode."""
    entries = {str(k): v["ros__parameters"] for k, v in data.items() if _entry_type(v)}
    systems = {k: v for k, v in entries.items() if v.get("type") == "system"}
    inner = {part for params in systems.values() for part in _parts(params)}
    problems: list[str] = []
    modes = []
    for name, params in systems.items():
        if name in inner:
            continue
        for mode in (params.get("modes") or {}):
            nodes: dict[str, dict] = {}
            _expand(entries, name, "active", str(mode), nodes, problems, 0)
            modes.append({"name": _mode_name(name, str(mode)), "nodes": nodes,
                          "description": f"system_modes: {name} in mode {mode}"})
    return modes, sorted(set(problems))


def _expand(entries: dict, name: str, state: str, mode: str, nodes: dict, problems: list[str], depth: int) -> None:
    """What ``name`` in ``state`` (and ``mode``) asks of the nodes it is made of."""
    params = entries.get(name)
    if params is None:
        problems.append(_("%(name)s is named as a part but not described in the file.") % {"name": name})
        return
    if depth > MAX_DEPTH:
        problems.append(_("%(name)s: systems nested deeper than %(depth)s (a loop?).") % {
            "name": name, "depth": MAX_DEPTH})
        return
    if params.get("type") == "node":
        wanted = (params.get("modes") or {}).get(mode) or {}
        values = wanted.get("ros__parameters") if isinstance(wanted, dict) else None
        if state == "active" and mode != DEFAULT and values is None:
            problems.append(_("%(name)s has no mode %(mode)s.") % {"name": name, "mode": mode})
        entry: dict[str, Any] = {"state": state}
        if state == "active" and isinstance(values, dict) and values:
            entry["parameters"] = dict(values)
        nodes[_node_name(name)] = entry
        return
    targets = (params.get("modes") or {}).get(mode)
    if not isinstance(targets, dict):
        problems.append(_("system %(name)s has no mode %(mode)s.") % {"name": name, "mode": mode})
        return
    for part in _parts(params):
        target = str(targets.get(part, state if state != "active" else "active"))
        part_state, _dot, part_mode = target.partition(".")
        if part_state not in definitions.STATES:
            problems.append(_("%(name)s: %(part)s is asked to be %(state)s, not a state a mode can ask for.") % {
                "name": name, "part": part, "state": repr(part_state)})
            continue
        # A system that is not active takes its parts down with it.
        if state != "active":
            part_state, part_mode = _lower(state, part_state), ""
        _expand(entries, part, part_state, part_mode or DEFAULT, nodes, problems, depth + 1)
    unknown = set(targets) - set(_parts(params))
    problems += [_("system %(name)s, mode %(mode)s: %(part)s is not one of its parts.") % {
        "name": name, "mode": mode, "part": part} for part in sorted(unknown)]


def _lower(a: str, b: str) -> str:
    order = list(definitions.STATES)  # unconfigured, inactive, active
    return order[min(order.index(a), order.index(b))]
