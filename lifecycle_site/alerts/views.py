"""The alerts page (viewers see, operators acknowledge) and the header's count (polled by htmx)."""
from __future__ import annotations

from django.contrib.auth.decorators import login_required
from django.http import HttpRequest, HttpResponse
from django.shortcuts import redirect, render
from django.utils.html import format_html
from django.utils.translation import gettext as _
from django.utils.translation import pgettext_lazy
from django.views.decorators.http import require_POST

from lifecycle_site.alerts import lifecycle
from lifecycle_site.audit import denials
from lifecycle_site.refusal import Refusal

PAGE_LIMIT = 200
STATUSES = [("recent", pgettext_lazy("alert status", "active, and resolved in the last hour")),
            ("active", pgettext_lazy("alert status", "active")), ("firing", pgettext_lazy("alert status", "firing")),
            ("acknowledged", pgettext_lazy("alert status", "acknowledged")),
            ("resolved", pgettext_lazy("alert status", "resolved")), ("all", pgettext_lazy("alert status", "all"))]
# htmx stops polling on this status: a signed-out page no longer asks (and is not sent the login page).
STOP_POLLING = 286


def _viewer(request: HttpRequest) -> bool:
    return request.user.has_perm(lifecycle.VIEW_PERMISSION)


@login_required
def alert_list(request: HttpRequest) -> HttpResponse:
    if not _viewer(request):
        return render(request, "dashboard/no_role.html", status=403)
    status = request.GET.get("status", "recent")
    if status not in dict(STATUSES):
        status = "recent"
    alerts = list(lifecycle.listed(status)[:PAGE_LIMIT])
    context = {"alerts": alerts, "status": status, "statuses": STATUSES, "limit": PAGE_LIMIT,
               "can_acknowledge": request.user.has_perm(lifecycle.ACKNOWLEDGE_PERMISSION)}
    template = "alerts/_rows.html" if request.htmx and request.htmx.target == "alert-rows" else "alerts/list.html"
    return render(request, template, context)


@login_required
@require_POST
def acknowledge(request: HttpRequest, alert_id: int) -> HttpResponse:
    """The Acknowledge button: htmx swaps in the alert's row; without JavaScript, back to the list."""
    if not request.user.has_perm(lifecycle.ACKNOWLEDGE_PERMISSION):
        denials.record(request, 403, "forbidden", "operator needed")
        return HttpResponse(format_html('<p class="result fail" role="alert">{}</p>', _(
            "Your role may view alerts but not acknowledge them (operator needed).")), status=403)
    error = ""
    try:
        alert = lifecycle.acknowledge(alert_id, request.user)
    except Refusal as refused:
        if refused.status == 404:
            return HttpResponse(format_html('<p class="result fail" role="alert">{}</p>', refused.message), status=404)
        error = refused.message
        alert = lifecycle.listed("all").get(pk=alert_id)
    if not request.htmx:
        return redirect("alerts:list")
    context = {"alert": alert, "can_acknowledge": True, "error": error}
    response = render(request, "alerts/_row.html", context)
    response["HX-Trigger"] = "alerts-changed"  # the header's count follows at once
    return response


def count(request: HttpRequest) -> HttpResponse:
    """The header's count of firing alerts, polled every few seconds."""
    if not request.user.is_authenticated or not _viewer(request):
        return HttpResponse(status=STOP_POLLING)
    return render(request, "alerts/_count.html", {"alert_counts": lifecycle.counts()})
