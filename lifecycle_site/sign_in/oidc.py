"""Sign-in with the company's OpenID Connect provider (mozilla-django-oidc: authorization code
flow with PKCE and nonce). What this module adds:

- the account is found again by the provider's subject (``sub``), never by e-mail; a new one
  gets the provider's user name unless a local account has it;
- the role comes from the groups claim (ID token or userinfo) at every sign-in; none mapped,
  no login;
- every failure of the provider (unreachable, refusing, answering nonsense) is a refusal in
  words on the login page and on record, never an error page;
- endpoints not set one by one come from the provider's discovery document (sign_in.discovery).
"""
from __future__ import annotations

import hashlib
import logging

import requests
from django.conf import settings
from django.contrib.auth import get_user_model
from django.core.exceptions import SuspiciousOperation
from django.db import transaction
from django.http import Http404, HttpRequest, HttpResponse
from django.shortcuts import redirect
from mozilla_django_oidc.auth import OIDCAuthenticationBackend
from mozilla_django_oidc.views import OIDCAuthenticationCallbackView, OIDCAuthenticationRequestView

from lifecycle_site.sign_in import accounts, discovery, problems
from lifecycle_site.sign_in.models import DirectoryAccount

log = logging.getLogger("lifecycle.sign_in")
MAX_GROUP_LENGTH = 256


def _text(claims: dict, name: str, field: str) -> str:
    """Claim ``name`` for the user field ``field``, cut to fit ("" unless the claim is text)."""
    value = claims.get(name)
    return accounts.fitted(field, value) if isinstance(value, str) else ""


def groups_in(claims: dict) -> list[str]:
    """The groups claim as a bounded list of names (a list, or one space-separated string)."""
    value = claims.get(settings.LIFECYCLE_OIDC_GROUPS_CLAIM)
    if isinstance(value, str):
        value = value.split()
    if not isinstance(value, list):
        return []
    return [g[:MAX_GROUP_LENGTH] for g in value[:accounts.MAX_GROUPS] if isinstance(g, str)]


class Backend(OIDCAuthenticationBackend):
    def authenticate(self, request, **kwargs):
        if request is None or "code" not in request.GET:
            return None  # a password login: not ours
        try:
            found = discovery.endpoints()
        except discovery.DiscoveryFailed as failed:
            problems.note(request, failed.problem)
            return None
        self.OIDC_OP_TOKEN_ENDPOINT = found["OIDC_OP_TOKEN_ENDPOINT"]
        self.OIDC_OP_USER_ENDPOINT = found["OIDC_OP_USER_ENDPOINT"]
        self.OIDC_OP_JWKS_ENDPOINT = found["OIDC_OP_JWKS_ENDPOINT"]
        try:
            with transaction.atomic():
                user = super().authenticate(request, **kwargs)
        except requests.exceptions.HTTPError as error:  # the token endpoint said no (code used, PKCE mismatch)
            log.warning("OIDC provider refused the sign-in: %s", error)
            problems.note(request, problems.PROVIDER_REFUSED)
            return None
        except requests.exceptions.JSONDecodeError as error:
            log.warning("OIDC provider answered with something that is not JSON: %s", error)
            problems.note(request, problems.PROVIDER_ANSWER_INVALID)
            return None
        except requests.exceptions.RequestException as error:
            log.warning("OIDC provider unreachable: %s", error)
            problems.note(request, problems.PROVIDER_UNREACHABLE)
            return None
        except Exception:  # a stranger's answer (token, keys, claims) we could not use: refuse, in words
            log.exception("OIDC provider's answer could not be verified")
            problems.note(request, problems.PROVIDER_ANSWER_INVALID)
            return None
        if user is not None and not user.is_active:
            problems.note(request, problems.ACCOUNT_OFF)
            return None
        if user is None and problems.noted(request) is None:
            problems.note(request, problems.PROVIDER_ANSWER_INVALID)
        return user

    def get_userinfo(self, access_token, id_token, payload):
        """The ID token's claims with the userinfo endpoint's over them: some providers put the
        groups only in the ID token, others only in userinfo."""
        userinfo = super().get_userinfo(access_token, id_token, payload)
        if not isinstance(userinfo, dict):
            raise SuspiciousOperation("userinfo is not a JSON object")
        if userinfo.get("sub") not in (None, payload.get("sub")):
            raise SuspiciousOperation("userinfo is about another subject than the ID token")
        return {**payload, **userinfo}

    def verify_claims(self, claims) -> bool:
        if not isinstance(claims.get("sub"), str) or not claims["sub"]:
            raise SuspiciousOperation("no subject in the provider's claims")
        role = accounts.role_for(groups_in(claims), settings.LIFECYCLE_OIDC_ROLES)
        if role is None:
            log.warning("OIDC subject %s has no mapped group (groups: %s)", claims["sub"],
                        ", ".join(groups_in(claims)) or "none")
            problems.note(self.request, problems.NO_ROLE)
            return False
        return True

    def filter_users_by_claims(self, claims):
        user = accounts.user_of(DirectoryAccount.OIDC, claims["sub"][:255])
        return [user] if user is not None else []

    def create_user(self, claims):
        user = get_user_model().objects.create_user(self._free_username(claims))  # no password: the provider's
        return self.update_user(user, claims)  # its e-mail, names, role

    def update_user(self, user, claims):
        for field, claim in (("email", "email"), ("first_name", "given_name"), ("last_name", "family_name")):
            if _text(claims, claim, field):
                setattr(user, field, _text(claims, claim, field))
        user.save()
        groups = groups_in(claims)
        accounts.signed_in(user, DirectoryAccount.OIDC, claims["sub"][:255],
                           accounts.role_for(groups, settings.LIFECYCLE_OIDC_ROLES), groups)
        return user

    def get_user(self, user_id):
        user = super().get_user(user_id)
        return user if user is not None and user.is_active else None

    @staticmethod
    def _free_username(claims: dict) -> str:
        """The provider's user name (else the e-mail, else the subject); with a part of the
        subject's hash after it when another account already has that name."""
        wanted = (_text(claims, "preferred_username", "username") or _text(claims, "email", "username")
                  or claims["sub"])[:130]
        users = get_user_model().objects
        if not users.filter(username=wanted).exists():
            return wanted
        return f"{wanted}-{hashlib.sha256(claims['sub'].encode()).hexdigest()[:8]}"


class CallbackView(OIDCAuthenticationCallbackView):
    """The provider sends the browser back here; every failure ends on the login page, in words."""

    def get(self, request):
        try:
            return super().get(request)
        except SuspiciousOperation:  # a state this browser did not start (another tab, a replay)
            problems.note(request, problems.SIGN_IN_EXPIRED)
            return self.login_failure()

    def login_failure(self):
        return refused(self.request, hasattr(self, "user"))


class StartView(OIDCAuthenticationRequestView):
    """To the provider's authorization endpoint (as set, or from its discovery document)."""

    def get(self, request):
        try:
            self.OIDC_OP_AUTH_ENDPOINT = discovery.endpoints()["OIDC_OP_AUTHORIZATION_ENDPOINT"]
        except discovery.DiscoveryFailed as failed:
            problems.note(request, failed.problem)
            return refused(request, recorded=False)
        return super().get(request)


def refused(request: HttpRequest, recorded: bool) -> HttpResponse:
    """Back to the login page, which says why. ``recorded``: authenticate() ran, so its
    user_login_failed put the refusal on record already."""
    problem = problems.noted(request)
    if problem is None:
        if getattr(request, "axes_locked_out", False):
            problem = problems.BLOCKED
        elif request.GET.get("error"):  # the user declined, or the provider refused
            problem = problems.PROVIDER_REFUSED
        else:
            problem = problems.SIGN_IN_EXPIRED
    if not recorded:
        from lifecycle_site.audit import denials

        denials.record(request, 401, "login_failed", problem.summary)
    request.session[problems.SESSION_KEY] = problem.code
    return redirect(settings.LOGIN_URL)


def start(request: HttpRequest) -> HttpResponse:
    """GET /oidc/authenticate/: to the provider, with state, nonce and the PKCE challenge."""
    if not settings.OIDC_ON:
        raise Http404("Sign-in with OpenID Connect is not configured on this site.")
    return StartView.as_view()(request)


def callback(request: HttpRequest) -> HttpResponse:
    """GET /oidc/callback/: back from the provider."""
    if not settings.OIDC_ON:
        raise Http404("Sign-in with OpenID Connect is not configured on this site.")
    return CallbackView.as_view()(request)
