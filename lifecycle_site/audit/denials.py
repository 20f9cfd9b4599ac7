"""Refused attempts on record: who (account or address), what, when, and why refused.
One row per refusal, the newest DENIALS_KEPT kept: a flood of bad requests cannot fill the
database, and what an admin reviews is the latest."""
from __future__ import annotations

import logging
from datetime import datetime
from itertools import count

from django.contrib.auth.signals import user_login_failed
from django.db import DatabaseError
from django.http import HttpRequest

from lifecycle_site.audit.models import AccessDenial

log = logging.getLogger("lifecycle.denials")

DENIALS_KEPT = 10_000
PRUNE_EVERY = 100  # inserts between two prunes
_inserted = count(1)


def record(request: HttpRequest | None, status: int, code: str, detail: str = "", username: str = "") -> None:
    """Write the refusal; never lets the recording fail the answer."""
    user = getattr(request, "user", None) if request is not None else None
    user = user if getattr(user, "is_authenticated", False) else None
    name = _storable(username or (user.get_username() if user is not None else ""))
    client = (request.META.get("REMOTE_ADDR", "") if request is not None else "")[:64]
    method = _storable(request.method or "") if request is not None else ""
    path = _storable(request.path)[:300] if request is not None else ""
    detail = _storable(detail)
    log.warning("refused %s %s (%s %s) for %s from %s", method, path, status, code, name or "anonymous", client)
    try:
        AccessDenial.objects.create(user=user, username=name[:150], client=client, method=method[:8], path=path,
                                    status=status, code=code[:32], detail=detail[:200])
        if next(_inserted) % PRUNE_EVERY == 0:
            prune()
    except DatabaseError:
        log.exception("could not record a refused attempt")


def _storable(text: str) -> str:
    """What an attacker sent, as PostgreSQL can store it: a NUL character (``%00`` in a path or
    a user name tried) becomes U+FFFD instead of losing the whole record."""
    return text.replace("\x00", "\ufffd")


def token_block_until(request: HttpRequest) -> datetime | None:
    """When this client's block for token guessing ends, or None if it is not blocked.

    Blocked while AXES_FAILURE_LIMIT x 4 of its invalid bearer tokens fall within the login
    lock-out time: until the oldest of its newest that many leaves it. Requests refused while
    blocked (token_blocked) are not counted, so the end does not move while it waits."""
    from django.conf import settings
    from django.utils import timezone

    since = timezone.now() - settings.AXES_COOLOFF_TIME
    limit = settings.AXES_FAILURE_LIMIT * 4
    client = request.META.get("REMOTE_ADDR", "")[:64]
    oldest = (AccessDenial.objects.filter(code="bad_token", client=client, at__gte=since)
              .order_by("-at", "-id").values_list("at", flat=True)[limit - 1:limit].first())
    return None if oldest is None else oldest + settings.AXES_COOLOFF_TIME


def prune(keep: int = DENIALS_KEPT) -> int:
    cutoff = AccessDenial.objects.order_by("-id").values_list("id", flat=True)[keep:keep + 1].first()
    if cutoff is None:
        return 0
    deleted, _ = AccessDenial.objects.filter(id__lte=cutoff).delete()
    return deleted


def csrf_failure(request: HttpRequest, reason: str = ""):
    """CSRF_FAILURE_VIEW: on record, then Django's own answer."""
    from django.views.csrf import csrf_failure as django_csrf_failure

    record(request, 403, "csrf_failed", reason)
    return django_csrf_failure(request, reason=reason)


def permission_denied(request: HttpRequest, exception: Exception | None = None):
    """handler403: a refused change on record, then Django's own answer."""
    from django.views.defaults import permission_denied as django_permission_denied

    if request.method not in ("GET", "HEAD", "OPTIONS"):
        record(request, 403, "forbidden", str(exception or "")[:200])
    return django_permission_denied(request, exception)


def _login_failed(sender, credentials: dict, request: HttpRequest | None = None, **_) -> None:
    username = str(credentials.get("username", ""))
    if getattr(request, "axes_locked_out", False):  # django-axes: refused before the password was checked
        record(request, 429, "login_blocked", "too many failed logins for this account or address", username=username)
    else:
        # A company sign-in refused for a reason of its own (sign_in/problems.py notes it on the request).
        problem = getattr(request, "sign_in_problem", None)
        record(request, 401, "login_failed", problem.summary if problem else "wrong user name or password",
               username=username)


user_login_failed.connect(_login_failed, dispatch_uid="audit.denials.login_failed")
