"""Who may see the pages: any role (viewer, operator, admin); an account without one is told so."""
from __future__ import annotations

from functools import wraps

from django.contrib.auth.decorators import login_required
from django.http import HttpRequest, HttpResponse
from django.shortcuts import render
from django.utils.html import format_html
from django.utils.translation import gettext as _

from lifecycle_site.audit import denials

VIEW_PERMISSION = "fleet.view_managednode"


def viewer_required(view):
    @login_required
    @wraps(view)
    def wrapper(request, *args, **kwargs):
        if not request.user.has_perm(VIEW_PERMISSION):
            return render(request, "dashboard/no_role.html", status=403)
        return view(request, *args, **kwargs)

    return wrapper


def operator_required(view):
    """For changes: the operator role (or admin); others get a readable refusal."""

    @viewer_required
    @wraps(view)
    def wrapper(request, *args, **kwargs):
        if not request.user.has_perm("fleet.operate_node"):
            denials.record(request, 403, "forbidden", "operator needed")
            return HttpResponse(
                format_html('<p class="result fail" role="alert">{}</p>',
                            _("Your role may view but not operate nodes (operator needed).")),
                status=403,
            )
        return view(request, *args, **kwargs)

    return wrapper


def refresh_page() -> HttpResponse:
    """htmx reloads the page (which then says why: the login form, the no-role page, the 404)."""
    response = HttpResponse(status=204)
    response["HX-Refresh"] = "true"
    return response


def polled(view):
    """For the part the page polls: a session that has ended or lost its role reloads the page
    instead of swapping the login page into the table (login_required would redirect there)."""

    @wraps(view)
    def wrapper(request: HttpRequest, *args, **kwargs) -> HttpResponse:
        if not request.user.is_authenticated or not request.user.has_perm(VIEW_PERMISSION):
            return refresh_page()
        return view(request, *args, **kwargs)

    return wrapper
