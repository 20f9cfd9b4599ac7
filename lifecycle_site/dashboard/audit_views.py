"""Audit history: filter, page through, export as CSV. Read-only by construction."""
from __future__ import annotations

import csv
import json
import re

from django import forms
from django.core.exceptions import NON_FIELD_ERRORS
from django.core.paginator import Paginator
from django.db.models import QuerySet
from django.http import HttpRequest, HttpResponse
from django.shortcuts import render
from django.utils import timezone
from django.utils.translation import gettext as _
from django.utils.translation import gettext_lazy

from lifecycle_site.audit.models import ParameterRecord, TransitionRecord
from lifecycle_site.dashboard.access import viewer_required

PAGE_SIZE = 50
CSV_LIMIT = 100_000
# A spreadsheet runs a cell starting with one of these as a formula (OWASP "CSV injection"):
# such cells get a leading apostrophe. Plain numbers ("-0.5") are left as they are.
FORMULA_START = ("=", "+", "-", "@", "\t", "\r")
PLAIN_NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?")


def _cell(value: object) -> object:
    if isinstance(value, str) and value.startswith(FORMULA_START) and not PLAIN_NUMBER.fullmatch(value):
        return "'" + value
    return value


class _SafeWriter:
    """csv.writer whose text cells cannot start a formula in a spreadsheet."""

    def __init__(self, out) -> None:
        self._writer = csv.writer(out)

    def writerow(self, row: list) -> None:
        self._writer.writerow([_cell(value) for value in row])


WHEN_INVALID = gettext_lazy("Not a date and time: write it like 2026-11-23 14:05 (UTC), or pick it in the calendar.")
ANY = gettext_lazy("any")


class AuditFilter(forms.Form):
    kind = forms.ChoiceField(required=False, label=gettext_lazy("Changes of"),
                             choices=[("", gettext_lazy("lifecycle state")),
                                      ("parameters", gettext_lazy("parameters"))])
    robot = forms.CharField(required=False, label=gettext_lazy("Robot"))
    node = forms.CharField(required=False, label=gettext_lazy("Node"),
                           help_text=gettext_lazy("ROS name, e.g. /lidar_driver"))
    user = forms.CharField(required=False, label=gettext_lazy("User"))
    outcome = forms.ChoiceField(required=False, label=gettext_lazy("Outcome"),
                                choices=[("", ANY)] + TransitionRecord.Outcome.choices)
    source = forms.ChoiceField(required=False, label=gettext_lazy("Source"),
                               choices=[("", ANY)] + TransitionRecord.Source.choices)
    since = forms.DateTimeField(required=False, label=gettext_lazy("From (UTC)"),
                                error_messages={"invalid": WHEN_INVALID},
                                widget=forms.DateTimeInput(attrs={"type": "datetime-local"}))
    until = forms.DateTimeField(required=False, label=gettext_lazy("To (UTC)"),
                                error_messages={"invalid": WHEN_INVALID},
                                widget=forms.DateTimeInput(attrs={"type": "datetime-local"}))

    def clean(self):
        data = super().clean()
        if data.get("since") and data.get("until") and data["since"] > data["until"]:
            raise forms.ValidationError(_("'From' must be before 'to'."))
        return data

    @property
    def problems(self) -> list[str]:
        """Why the filter cannot be applied, one line per field, in the field's own words."""
        if not self.is_bound or self.is_valid():
            return []
        lines = [f"{self[name].label}: {' '.join(errors)}" for name, errors in self.errors.items()
                 if name != NON_FIELD_ERRORS]
        return lines + list(self.non_field_errors())

    @property
    def parameters(self) -> bool:
        return self.is_bound and self.is_valid() and self.cleaned_data.get("kind") == "parameters"

    def apply(self, records: QuerySet) -> QuerySet:
        data = self.cleaned_data
        when = "at" if records.model is ParameterRecord else "requested_at"
        if data.get("robot"):
            records = records.filter(robot_name__icontains=data["robot"])
        if data.get("node"):
            records = records.filter(node_name__icontains=data["node"])
        if data.get("user"):
            records = records.filter(requested_by_name__icontains=data["user"])
        if data.get("outcome"):
            records = records.filter(outcome=data["outcome"])
        if data.get("source"):
            records = records.filter(source=data["source"])
        if data.get("since"):
            records = records.filter(**{f"{when}__gte": data["since"]})
        if data.get("until"):
            records = records.filter(**{f"{when}__lte": data["until"]})
        return records


def filtered(query) -> tuple[AuditFilter, QuerySet]:
    """The filter form of a query string and the records it selects (none while it is invalid:
    the page then says why instead of showing an empty history as if it were the answer)."""
    form = AuditFilter(query or None)
    model = ParameterRecord if form.parameters else TransitionRecord
    records = model.objects.select_related("node")
    if form.is_bound and form.is_valid():
        records = form.apply(records)
    elif form.is_bound:
        records = records.none()
    return form, records


def _records(request: HttpRequest) -> tuple[AuditFilter, QuerySet]:
    return filtered(request.GET)


def live_query(request: HttpRequest, form: AuditFilter, records: QuerySet, page) -> str | None:
    """The query string of the page's live socket: its filter and the newest record shown.
    None where new records would not show (a later page, an invalid filter)."""
    if page.number != 1 or (form.is_bound and not form.is_valid()):
        return None
    query = request.GET.copy()
    query.pop("page", None)
    query["shown"] = str(records.order_by("-id").values_list("id", flat=True).first() or 0)
    return query.urlencode()


@viewer_required
def audit_list(request: HttpRequest) -> HttpResponse:
    form, records = _records(request)
    page = Paginator(records, PAGE_SIZE).get_page(request.GET.get("page"))
    query = request.GET.copy()
    query.pop("page", None)
    return render(
        request,
        "dashboard/audit.html",
        {"form": form, "page": page, "records": [r.as_dict() for r in page], "query": query.urlencode(),
         "parameters": form.parameters, "total": page.paginator.count, "problems": form.problems,
         "live_query": live_query(request, form, records, page)},
    )


@viewer_required
def audit_csv(request: HttpRequest) -> HttpResponse:
    form, records = _records(request)
    response = HttpResponse(content_type="text/csv; charset=utf-8")
    kind = "parameters" if form.parameters else "transitions"
    response["Content-Disposition"] = f'attachment; filename="audit-{kind}-{timezone.now():%Y%m%d-%H%M%S}.csv"'
    writer = _SafeWriter(response)
    if form.parameters:
        writer.writerow(["at", "robot", "node", "parameter", "old", "new", "outcome", "source", "user", "reason"])
        for r in records[:CSV_LIMIT].iterator(chunk_size=2000):
            writer.writerow([r.at.isoformat(), r.robot_name, r.node_name, r.name, json.dumps(r.old_value),
                             json.dumps(r.new_value), r.outcome, r.source, r.requested_by_name, r.reason])
        return response
    writer.writerow(["requested_at", "completed_at", "robot", "node", "transition", "from", "goal", "result",
                     "outcome", "source", "user", "duration_ms", "run_id", "error"])
    for r in records[:CSV_LIMIT].iterator(chunk_size=2000):
        writer.writerow([
            r.requested_at.isoformat(), r.completed_at.isoformat() if r.completed_at else "", r.robot_name,
            r.node_name, r.transition_label, r.start_state_label, r.goal_state_label, r.result_state_label,
            r.outcome, r.source, r.requested_by_name, "" if r.duration_ms is None else f"{r.duration_ms:.1f}",
            r.run_id, r.error,
        ])
    return response
