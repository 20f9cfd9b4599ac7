"""Whether an open live socket may still receive updates: its session still exists (no
logout), is still its user's (password unchanged), the user is active and still has a role
that may view.

Every socket asks every few seconds. A control room's screens share a handful of sessions,
so the answer is kept per session for SESSION_CHECK_TTL_S: fifty sockets of one session cost
one check a second, not fifty every three seconds (each a session, a user and two permission
queries on a fresh database connection).
"""
from __future__ import annotations

from dataclasses import dataclass
from importlib import import_module

from django.conf import settings
from django.contrib.auth import HASH_SESSION_KEY, SESSION_KEY, get_user_model
from django.core.cache import cache
from django.utils.crypto import constant_time_compare

NOT_LOGGED_IN = 4401
NO_ROLE = 4403
VIEW_PERMISSION = "fleet.view_managednode"
OPERATE_PERMISSION = "fleet.operate_node"
SESSION_CHECK_TTL_S = 1.0


@dataclass(frozen=True)
class Verdict:
    refusal: int | None  # a close code, or None: the socket may stay
    user_id: int | None
    can_operate: bool


def check_session(session_key: str | None) -> Verdict:
    """The session's verdict, read afresh at most once per SESSION_CHECK_TTL_S (kept in the
    process's own memory: Django's default local-memory cache)."""
    if session_key is None:
        return Verdict(NOT_LOGGED_IN, None, False)
    return cache.get_or_set(f"socket-session:{session_key}", lambda: _read(session_key), SESSION_CHECK_TTL_S)


def _read(session_key: str) -> Verdict:
    store = import_module(settings.SESSION_ENGINE).SessionStore(session_key)
    data = store.load()  # empty when the session is gone
    user = get_user_model().objects.filter(pk=data.get(SESSION_KEY), is_active=True).first()
    if user is None:
        return Verdict(NOT_LOGGED_IN, None, False)
    if not constant_time_compare(data.get(HASH_SESSION_KEY, ""), user.get_session_auth_hash()):
        return Verdict(NOT_LOGGED_IN, user.pk, False)
    if not user.has_perm(VIEW_PERMISSION):
        return Verdict(NO_ROLE, user.pk, False)
    return Verdict(None, user.pk, user.has_perm(OPERATE_PERMISSION))
