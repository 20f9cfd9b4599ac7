"""Why a company sign-in was refused, in the operator's words.

A backend notes the problem on the request (``note``); the login form shows it and the refusal
is recorded with it (audit/denials.py). The codes are stable: tests and the audit record use them."""
from __future__ import annotations

from dataclasses import dataclass

from django.http import HttpRequest
from django.utils.functional import Promise
from django.utils.translation import gettext_lazy as _


@dataclass(frozen=True)
class Problem:
    code: str
    words: str | Promise  # for the person signing in, in their language
    summary: str  # for the record of refused attempts (stored in English)


DIRECTORY_UNREACHABLE = Problem(
    "directory_unreachable",
    _("The company directory could not be reached, so your password could not be checked. Try again in a "
      "minute; if it persists, tell your IT department (local accounts still work)."),
    "company directory unreachable (or its TLS certificate not accepted)")
NO_ROLE = Problem(
    "no_role",
    _("Your company account is not in any group that gives a role in the lifecycle manager. Ask your "
      "administrator to add you to the viewer, operator or admin group."),
    "directory account in no group mapped to a role")
LOCAL_NAME = Problem(
    "local_name",
    _("A local account has this name: sign in with its own password."),
    "directory sign-in refused: a local account has this name")
PROVIDER_UNREACHABLE = Problem(
    "provider_unreachable",
    _("The company sign-in service could not be reached. Try again in a minute; if it persists, tell your IT "
      "department (local accounts still work)."),
    "OIDC provider unreachable")
PROVIDER_REFUSED = Problem(
    "provider_refused",
    _("The company sign-in service did not confirm your sign-in. Please sign in again."),
    "OIDC provider refused or the user declined")
PROVIDER_ANSWER_INVALID = Problem(
    "provider_answer_invalid",
    _("The company sign-in service answered in a way that could not be verified, so you were not signed in. "
      "Tell your administrator (the site's log has the details)."),
    "OIDC provider's answer could not be verified")
SIGN_IN_EXPIRED = Problem(
    "sign_in_expired",
    _("This sign-in was started in another tab or has expired. Please sign in again."),
    "OIDC sign-in state unknown (another tab, expired or replayed)")
BLOCKED = Problem(
    "login_blocked",
    _("Too many failed sign-ins from this address: signing in is blocked for a while."),
    "too many failed logins for this account or address")
ACCOUNT_OFF = Problem(
    "account_off",
    _("This account is switched off in the lifecycle manager. Ask an administrator."),
    "account switched off")

BY_CODE = {p.code: p for p in (DIRECTORY_UNREACHABLE, NO_ROLE, LOCAL_NAME, PROVIDER_UNREACHABLE, PROVIDER_REFUSED,
                               PROVIDER_ANSWER_INVALID, SIGN_IN_EXPIRED, BLOCKED, ACCOUNT_OFF)}
SESSION_KEY = "sign_in_problem"  # carries an OIDC problem over the redirect to the login page


def note(request: HttpRequest | None, problem: Problem) -> None:
    if request is not None:
        request.sign_in_problem = problem


def noted(request: HttpRequest | None) -> Problem | None:
    return getattr(request, "sign_in_problem", None)
