"""The node page's parameter section: view, edit (checked before sending), import/export."""
from __future__ import annotations

import json
import math
import re
from typing import Any

from django.http import HttpRequest, HttpResponse
from django.shortcuts import render
from django.utils.translation import gettext as _
from django.views.decorators.http import require_POST

from lifecycle_site.api import limits
from lifecycle_site.api.auth import NonFiniteNumber, loads_finite
from lifecycle_site.dashboard.access import operator_required, viewer_required
from lifecycle_site.dashboard.views import node_or_404
from lifecycle_site.fleet.models import ManagedNode
from lifecycle_site.fleet.param_files import ParameterFileError, diff, load
from lifecycle_site.gateway_link.gateway_client import GatewayError
from lifecycle_site.operations.parameters import apply, fetch
from ros_gateway.shared import param_types as pt

MAX_FILE_BYTES = 256 * 1024
MAX_FILE_NAME = 200  # characters of an uploaded file's name shown back
# ROS descriptors have no field for a list of allowed values; nodes write it into the free-text
# additional_constraints, e.g. "one of: none, fail_configure" or "[low, high]". Bounded, so a
# long text stays text.
CHOICES = re.compile(r"(?:(?:one of|allowed(?: values)?|choices|values)\s*:?\s*(?P<words>.+))|\[(?P<list>.+)\]",
                     re.IGNORECASE)
MAX_CHOICES, MAX_CONSTRAINT_TEXT = 50, 500
CHOICE_TYPES = {"string": str, "integer": int, "double": float}


def choices(entry: dict) -> list[str] | None:
    """The values a parameter may take, as form values, when they form a fixed list: true and
    false for a bool; the list its additional_constraints names for a string or a number
    (every item must be of the parameter's type). None: a free field."""
    if entry["type"] == "bool":
        return ["true", "false"]
    convert = CHOICE_TYPES.get(entry["type"])
    text = (entry.get("additional_constraints") or "").strip().rstrip(".")
    if convert is None or not text or len(text) > MAX_CONSTRAINT_TEXT:
        return None
    found = CHOICES.fullmatch(text)
    if found is None:
        return None
    items = [i.strip().strip("'\"`") for i in re.split(r"[,|]", found["words"] or found["list"])]
    items = [i for i in items if i]
    # Values are single words ("fail_configure", "1.5"): "one of the camera modes, see the
    # manual" is prose, not a list.
    if not 2 <= len(items) <= MAX_CHOICES or any(re.search(r"\s", i) for i in items):
        return None
    try:
        return [_shown(convert(i)) for i in items]
    except ValueError:
        return None


def _with_choices(listing: list[dict], typed: dict[str, str] | None = None) -> list[dict]:
    """Each entry with its choices and the value its field shows: what the operator typed, for
    a value that was not set (so it can be corrected, not typed again), else the current one."""
    for entry in listing:
        entry["choices"] = choices(entry)
        shown = _shown(entry["value"]) if entry["type"] != "bool" else str(bool(entry["value"])).lower()
        # A value outside the list (set by another tool) stays selectable, so saving keeps it.
        entry["off_list"] = shown if entry["choices"] and shown not in entry["choices"] else None
        entry["typed"] = (typed or {}).get(entry["name"])
        entry["shown"] = entry["typed"] if entry["typed"] in (entry["choices"] or ()) else shown
    return listing


def _section(request: HttpRequest, node: ManagedNode, **extra) -> HttpResponse:
    context = {"node_obj": node, "can_operate": request.user.has_perm("fleet.operate_node"), **extra}
    if "parameters" not in context and "error" not in context:
        try:
            context["parameters"] = fetch(node) if node.alive else []
        except GatewayError as exc:
            context["error"] = exc.message
    if not node.alive and "error" not in context:
        context["error"] = _("The node is not running: its parameters cannot be read.")
    if context.get("parameters"):
        context["parameters"] = _with_choices(context["parameters"], context.get("typed"))
    return render(request, "dashboard/_parameters.html", context)


def _parse(raw: str, entry: dict) -> Any:
    """A form field as the parameter's type (the gateway checks ranges again). NaN and
    infinities are refused here: no record could store them and they are never meant."""
    kind = entry["type"]
    try:
        if kind == "integer":
            return int(raw)
        if kind == "double":
            value = float(raw)
            if not math.isfinite(value):
                raise NonFiniteNumber(raw.strip(), ())
            return value
        if kind.endswith("_array"):
            return loads_finite(raw)
    except NonFiniteNumber as exc:
        raise pt.InvalidValue(str(exc)) from None
    except ValueError:
        raise pt.InvalidValue(_("%(value)s is not a valid %(type)s") % {
            "value": repr(raw), "type": kind.replace("_", " ")}) from None
    return raw


@viewer_required
def parameters(request: HttpRequest, key: str) -> HttpResponse:
    node = node_or_404(key)
    if request.method != "POST":
        return _section(request, node)
    return _edit(request, node)


@operator_required
@require_POST
def _edit(request: HttpRequest, node: ManagedNode) -> HttpResponse:
    try:
        listing = fetch(node)
    except GatewayError as exc:
        return _section(request, node, error=exc.message)
    values, problems, typed = {}, {}, {}
    for entry in listing:
        name = entry["name"]
        if f"seen:{name}" not in request.POST or entry["read_only"]:
            continue
        if entry["type"] == "bool":
            raw = request.POST.get(f"value:{name}")
            if raw is None:
                continue
            if raw not in ("true", "false"):
                problems[name] = {"name": name, "successful": False,
                                  "reason": _("%(value)s is not true or false") % {"value": repr(raw)}}
                continue
            typed[name] = raw
            value = raw == "true"
        else:
            raw = request.POST.get(f"value:{name}", "")
            if raw == _shown(entry["value"]):
                continue
            typed[name] = raw
            try:
                value = _parse(raw, entry)
            except pt.InvalidValue as exc:
                problems[name] = {"name": name, "successful": False, "reason": str(exc)}
                continue
        if value != entry["value"]:
            values[name] = value
    results = {}
    if values:
        try:
            results = {r["name"]: r for r in apply(node, values, request.user, "dashboard")}
        except GatewayError as exc:
            return _section(request, node, parameters=listing, error=exc.message)
    results.update(problems)
    refused = {name: raw for name, raw in typed.items() if name in results and not results[name]["successful"]}
    return _section(request, node, results=results, nothing_changed=not results, typed=refused)


def _shown(value: Any) -> str:
    return json.dumps(value) if isinstance(value, list) else ("" if value is None else str(value))


def _preview(request: HttpRequest, node: ManagedNode, current: list[dict], changes: list[dict], file_name: str,
             **extra) -> HttpResponse:
    """The file's changes, each with why it is left out or the node's reason for refusing it;
    Apply sends the others, all together."""
    applicable = {c["name"]: c["value"] for c in changes if not c["note"]}
    return _section(request, node, parameters=current, preview=changes, file_name=file_name,
                    preview_values=json.dumps(applicable), applicable=len(applicable),
                    left_out=len(changes) - len(applicable), **extra)


@operator_required
@require_POST
def import_file(request: HttpRequest, key: str) -> HttpResponse:
    """Step 1: read an uploaded parameter file and show what it would change, checked as the
    gateway checks a value before it sends it."""
    node = node_or_404(key)
    upload = request.FILES.get("file")
    if upload is None:
        return _section(request, node, import_error=_("Choose a parameter file (.yaml) first."))
    if upload.size > MAX_FILE_BYTES:
        return _section(request, node, import_error=_("The file is larger than %(size)s KiB.") % {
            "size": MAX_FILE_BYTES // 1024})
    try:
        wanted = load(upload.read().decode("utf-8", errors="replace"), node.name)
        current = fetch(node)
    except ParameterFileError as exc:
        return _section(request, node, import_error=f"{upload.name}: {exc}")
    except GatewayError as exc:
        return _section(request, node, error=exc.message)
    return _preview(request, node, current, diff(current, wanted), upload.name[:MAX_FILE_NAME])


def _blame(changes: list[dict], results: dict[str, dict]) -> None:
    """Put the node's refusal beside the values it names: a node refusing a set of values says
    why once, for all of them (beside each value when it names none)."""
    refused = [r for r in results.values() if not r["successful"]]
    reason = refused[0]["reason"] if refused else ""
    named = {c["name"] for c in changes if c["name"] in reason}
    for change in changes:
        result = results.get(change["name"])
        if result is None or result["successful"]:
            continue
        if not named or change["name"] in named:
            change["refused"] = result["reason"]
        else:
            change["held"] = True  # not refused itself: went with the one that was


@operator_required
@require_POST
def apply_file(request: HttpRequest, key: str) -> HttpResponse:
    """Step 2: apply what the preview showed as valid, all or none. Checked again first (the
    node's values or the page may have changed since): nothing is sent if one fails."""
    node = node_or_404(key)
    file_name = request.POST.get("file_name", "")[:MAX_FILE_NAME] or _("the file")
    try:
        values = loads_finite(request.POST.get("values", "{}"))
        assert isinstance(values, dict)
    except NonFiniteNumber as exc:
        return _section(request, node, import_error=_("Nothing was sent: %(problem)s.") % {"problem": exc})
    except (ValueError, AssertionError):
        return _section(request, node, import_error=_("The preview was damaged; import the file again."))
    if not values:
        return _section(request, node, nothing_changed=True)
    if len(values) > limits.MAX_PARAMETERS:
        return _section(request, node, import_error=_(
            "The file sets %(count)s parameters; at most %(max)s can be set at once. Nothing was sent.") % {
            "count": len(values), "max": limits.MAX_PARAMETERS})
    try:
        current = fetch(node)
        changes = diff(current, values)
        if any(c["note"] for c in changes):
            return _preview(request, node, current, changes, file_name, apply_error=_(
                "Nothing was sent: the node's parameters changed since the preview, and some of these values "
                "no longer fit (the reason is beside each)."))
        sending = {c["name"]: c["value"] for c in changes}
        if not sending:
            return _section(request, node, parameters=current, nothing_changed=True)
        results = {r["name"]: r for r in apply(node, sending, request.user, "dashboard", atomic=True)}
        if all(r["successful"] for r in results.values()):
            return _section(request, node, results=results)
        # Refused: the file's values stay on the page with the node's reason beside them.
        current = fetch(node)
        changes = diff(current, values)
    except GatewayError as exc:
        return _section(request, node, error=exc.message)
    _blame(changes, results)
    return _preview(request, node, current, changes, file_name, apply_error=_refusal(results))


def _refusal(results: dict[str, dict]) -> str:
    if any(r["successful"] for r in results.values()):  # a gateway from before atomic sets
        return _("The node refused some of these values and took the others (its gateway sets them one at a "
                 "time); what it refused is beside each, its current values are above.")
    # (the gateway's words for a node that did not answer: ros_gateway, in English)
    if any(r["reason"].startswith("no answer from the node") for r in results.values()):
        return _("The node did not answer in time: these values may or may not be set. Its current values are "
                 "in the table above.")
    return _("Nothing was set: the node refused these values, and it takes them all together or none. "
             "Its reason is beside the value it refused.")
