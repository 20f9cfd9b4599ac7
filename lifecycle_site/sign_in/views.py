"""The login page (local accounts, and the company directory where configured) and logging out
(which also ends the OIDC provider's session when it has an end-session address)."""
from __future__ import annotations

from urllib.parse import urlencode

from django.conf import settings
from django.contrib.auth import views as auth_views
from django.http import HttpResponseRedirect
from django.shortcuts import resolve_url
from django.utils.translation import gettext as _

from lifecycle_site.login_form import LoginForm
from lifecycle_site.sign_in import discovery, problems


class Login(auth_views.LoginView):
    authentication_form = LoginForm

    def get_context_data(self, **kwargs):
        context = super().get_context_data(**kwargs)
        code = self.request.session.pop(problems.SESSION_KEY, None) if self.request.method == "GET" else None
        context.update(
            sign_in_problem=problems.BY_CODE.get(code) if code else None,
            oidc_name=(settings.LIFECYCLE_OIDC_NAME or _("company account")) if settings.OIDC_ON else "",
            ldap_on=settings.LDAP_ON,
        )
        return context


class Logout(auth_views.LogoutView):
    def post(self, request, *args, **kwargs):
        id_token = request.session.get("oidc_id_token")
        response = super().post(request, *args, **kwargs)
        if not id_token:
            return response
        end_session = discovery.end_session_url()
        if not end_session:
            return response
        back = request.build_absolute_uri(resolve_url(settings.LOGOUT_REDIRECT_URL))
        query = urlencode({"id_token_hint": id_token, "post_logout_redirect_uri": back,
                           "client_id": settings.OIDC_RP_CLIENT_ID})
        return HttpResponseRedirect(f"{end_session}{'&' if '?' in end_session else '?'}{query}")
