"""Audit history: filter, page through, export as CSV. Read-only by construction."""
from __future__ import annotations

import csv

from django import forms
from django.core.paginator import Paginator
from django.db.models import QuerySet
from django.http import HttpRequest, HttpResponse
from django.shortcuts import render
from django.utils import timezone

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.dashboard.access import viewer_required

PAGE_SIZE = 50
CSV_LIMIT = 100_000


class AuditFilter(forms.Form):
    robot = forms.CharField(required=False)
    node = forms.CharField(required=False, help_text="ROS name, e.g. /lidar_driver")
    user = forms.CharField(required=False)
    outcome = forms.ChoiceField(required=False, choices=[("", "any")] + TransitionRecord.Outcome.choices)
    source = forms.ChoiceField(required=False, choices=[("", "any")] + TransitionRecord.Source.choices)
    since = forms.DateTimeField(required=False, widget=forms.DateTimeInput(attrs={"type": "datetime-local"}))
    until = forms.DateTimeField(required=False, widget=forms.DateTimeInput(attrs={"type": "datetime-local"}))

    def clean(self):
        data = super().clean()
        if data.get("since") and data.get("until") and data["since"] > data["until"]:
            raise forms.ValidationError("'From' must be before 'to'.")
        return data

    def apply(self, records: QuerySet) -> QuerySet:
        data = self.cleaned_data
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
            records = records.filter(requested_at__gte=data["since"])
        if data.get("until"):
            records = records.filter(requested_at__lte=data["until"])
        return records


def _records(request: HttpRequest) -> tuple[AuditFilter, QuerySet]:
    form = AuditFilter(request.GET or None)
    records = TransitionRecord.objects.select_related("node")
    if form.is_bound and form.is_valid():
        records = form.apply(records)
    elif form.is_bound:
        records = records.none()
    return form, records


@viewer_required
def audit_list(request: HttpRequest) -> HttpResponse:
    form, records = _records(request)
    page = Paginator(records, PAGE_SIZE).get_page(request.GET.get("page"))
    query = request.GET.copy()
    query.pop("page", None)
    return render(
        request,
        "dashboard/audit.html",
        {"form": form, "page": page, "records": [r.as_dict() for r in page], "query": query.urlencode()},
    )


@viewer_required
def audit_csv(request: HttpRequest) -> HttpResponse:
    _, records = _records(request)
    response = HttpResponse(content_type="text/csv; charset=utf-8")
    response["Content-Disposition"] = f'attachment; filename="audit-{timezone.now():%Y%m%d-%H%M%S}.csv"'
    writer = csv.writer(response)
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
