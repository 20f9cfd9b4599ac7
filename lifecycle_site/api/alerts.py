"""Alert endpoints of the JSON API v1 (docs/api.md, "Alerts"): alerts (viewers read, operators
acknowledge) and alert rules (viewers read, admins create, change and delete)."""
from __future__ import annotations

from django import forms
from django.http import HttpRequest, JsonResponse
from django.urls import path
from django.utils.translation import gettext as _

from lifecycle_site.alerts import lifecycle
from lifecycle_site.alerts.models import Receiver, Rule
from lifecycle_site.api.auth import api_view, error, json_body, lacks_role
from lifecycle_site.audit import denials
from lifecycle_site.fleet.models import Gateway, Robot

MAX_LIMIT = 1000
RULE_FIELDS = ("name", "kind", "state", "for_seconds", "keep_firing_seconds", "gateway", "robot", "node_pattern",
               "status_pattern", "level", "receivers", "enabled")
NEW_RULE = {"for_seconds": 0.0, "keep_firing_seconds": 0.0, "enabled": True}
MANAGE_PERMISSIONS = {"POST": "alerts.add_rule", "PATCH": "alerts.change_rule", "DELETE": "alerts.delete_rule"}


class RuleForm(forms.ModelForm):
    """A rule as the API takes it: gateway, robot and receivers by name."""

    gateway = forms.ModelChoiceField(Gateway.objects.all(), to_field_name="name", required=False)
    robot = forms.ModelChoiceField(Robot.objects.all(), to_field_name="name", required=False)
    receivers = forms.ModelMultipleChoiceField(Receiver.objects.all(), to_field_name="name", required=False)

    class Meta:
        model = Rule
        fields = list(RULE_FIELDS)


def _refuse(request: HttpRequest, needed: str) -> JsonResponse:
    denials.record(request, 403, "forbidden", f"{needed} needed")  # (on record: in English)
    return error("forbidden", lacks_role(needed), 403)


def _alert_or_404(alert_id: int):
    return lifecycle.listed("all").filter(pk=alert_id).first()


@api_view()
def alerts(request: HttpRequest) -> JsonResponse:
    if not request.user.has_perm(lifecycle.VIEW_PERMISSION):
        return _refuse(request, "viewer")
    status = request.GET.get("status", "active")
    if status not in ("active", "all", *lifecycle.Alert.Status.values):
        return error("bad_status", _("status %(status)s is not one of active, firing, acknowledged, resolved, "
                                     "all.") % {"status": repr(status[:40])}, 400)
    try:
        limit = max(1, min(int(request.GET.get("limit", 100)), MAX_LIMIT))
    except ValueError:
        return error("bad_limit", _("limit must be a whole number (1-1000)."), 400)
    rows = lifecycle.listed(status)[:limit]
    return JsonResponse({"counts": lifecycle.counts(), "alerts": [a.as_dict() for a in rows]})


@api_view()
def alert_detail(request: HttpRequest, alert_id: int) -> JsonResponse:
    if not request.user.has_perm(lifecycle.VIEW_PERMISSION):
        return _refuse(request, "viewer")
    alert = _alert_or_404(alert_id)
    if alert is None:
        return error("not_found", _("There is no alert %(id)s.") % {"id": alert_id}, 404)
    return JsonResponse(alert.as_dict())


@api_view(methods=("POST",))
def acknowledge(request: HttpRequest, alert_id: int) -> JsonResponse:
    if not request.user.has_perm(lifecycle.ACKNOWLEDGE_PERMISSION):
        return _refuse(request, "operator or admin")
    return JsonResponse(lifecycle.acknowledge(alert_id, request.user).as_dict())


def _rules():
    return Rule.objects.select_related("gateway", "robot").prefetch_related("receivers")


def _save_rule(request: HttpRequest, instance: Rule | None) -> JsonResponse:
    body = json_body(request, shape=dict, wanted=_("of rule fields"))
    unknown = sorted(set(body) - set(RULE_FIELDS))
    if unknown:
        return error("unknown_fields", _("Unknown rule fields: %(unknown)s; use %(fields)s.") % {
            "unknown": ", ".join(map(str, unknown))[:200], "fields": ", ".join(RULE_FIELDS)}, 400)
    data = {**(instance.as_dict() if instance else NEW_RULE), **body}
    data = {k: ("" if v is None else v) for k, v in data.items() if k in RULE_FIELDS}
    form = RuleForm(data, instance=instance)
    if not form.is_valid():
        fields = {name: [str(m) for m in messages] for name, messages in form.errors.items()}
        first = "; ".join(f"{name}: {' '.join(messages)}" for name, messages in fields.items())
        return error("invalid_rule", _("The rule was not saved: %(problems)s") % {"problems": first}, 400,
                     fields=fields)
    rule = form.save()
    return JsonResponse(_rules().get(pk=rule.pk).as_dict(), status=200 if instance else 201)


@api_view(methods=("GET", "POST"))
def rules(request: HttpRequest) -> JsonResponse:
    if request.method == "POST":
        if not request.user.has_perm(MANAGE_PERMISSIONS["POST"]):
            return _refuse(request, "admin")
        return _save_rule(request, None)
    if not request.user.has_perm(lifecycle.VIEW_PERMISSION):
        return _refuse(request, "viewer")
    return JsonResponse({"rules": [r.as_dict() for r in _rules()]})


@api_view(methods=("GET", "PATCH", "DELETE"))
def rule_detail(request: HttpRequest, rule_id: int) -> JsonResponse:
    needed = MANAGE_PERMISSIONS.get(request.method, lifecycle.VIEW_PERMISSION)
    if not request.user.has_perm(needed):
        return _refuse(request, "viewer" if request.method == "GET" else "admin")
    rule = _rules().filter(pk=rule_id).first()
    if rule is None:
        return error("not_found", _("There is no alert rule %(id)s.") % {"id": rule_id}, 404)
    if request.method == "DELETE":
        rule.delete()  # its alerts stay (by rule name); an active one is resolved at the next evaluation
        return JsonResponse({"deleted": rule_id})
    if request.method == "PATCH":
        return _save_rule(request, rule)
    return JsonResponse(rule.as_dict())


urlpatterns = [
    path("alerts", alerts, name="alerts"),
    path("alerts/<int:alert_id>", alert_detail, name="alert"),
    path("alerts/<int:alert_id>/acknowledge", acknowledge, name="alert-acknowledge"),
    path("alert-rules", rules, name="alert-rules"),
    path("alert-rules/<int:rule_id>", rule_detail, name="alert-rule"),
]
