"""The "API tokens" page: any logged-in user makes and revokes their own bearer tokens, the way
personal access tokens work elsewhere. A token acts as its user: it never grants more than the
user has, and nothing without a role. The new token is shown once, in the answer to the POST
that made it (not stored, not in a message or a redirect)."""
from __future__ import annotations

from datetime import timedelta

from django.conf import settings
from django.contrib import messages
from django.contrib.auth.decorators import login_required
from django.http import HttpRequest, HttpResponse, HttpResponseRedirect
from django.shortcuts import get_object_or_404, render
from django.urls import reverse
from django.utils.translation import gettext as _
from django.views.decorators.http import require_POST

from lifecycle_site.api.models import MAX_TOKENS_PER_USER, ApiToken, TooManyTokens

VIA = "API tokens page"  # (stored in the token's audit record: in English)


def _page(request: HttpRequest, status: int = 200, **extra) -> HttpResponse:
    account = getattr(request.user, "directory_account", None)  # a company directory's account (sign_in)
    vouched = account.vouched if account is not None else None
    days = settings.LIFECYCLE_DIRECTORY_TOKEN_DAYS
    context = {
        # Its tokens work until then (api/auth.py, _dormant); each sign-in moves it on.
        "directory_until": vouched + timedelta(days=days) if vouched else None,
        "directory_days": f"{days:g}",
        "tokens": ApiToken.objects.filter(user=request.user),
        "max_tokens": MAX_TOKENS_PER_USER,
        "has_role": request.user.has_perm("fleet.view_managednode"),
        **extra,
    }
    return render(request, "dashboard/tokens.html", context, status=status)


@login_required
def my_tokens(request: HttpRequest) -> HttpResponse:
    if request.method != "POST":
        return _page(request)
    name = request.POST.get("name", "").strip()
    if not name:
        return _page(request, 400, error=_("Name the token after what will use it (e.g. 'CI bring-up')."), name=name)
    if len(name) > 100:
        return _page(request, 400, error=_("The name is longer than %(max)s characters.") % {"max": 100}, name=name)
    try:
        record, token = ApiToken.issue(request.user, name, by=request.user, via=VIA)
    except TooManyTokens as exc:
        return _page(request, 400, error=str(exc), name=name)
    return _page(request, 201, new_token=token, new_record=record)


@login_required
@require_POST
def revoke_token(request: HttpRequest, token_id: int) -> HttpResponse:
    # Another user's token is "not found": its existence is none of this user's business.
    record = get_object_or_404(ApiToken, pk=token_id, user=request.user)
    record.revoke(by=request.user, via=VIA)
    messages.success(request, _("Token %(hint)s… (%(name)s) revoked: it no longer works.") % {
        "hint": record.hint, "name": record.name or _("no name")})
    return HttpResponseRedirect(reverse("dashboard:tokens"))
