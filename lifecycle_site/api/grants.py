"""What a bearer token grants (its user and their permissions), kept per process for a few
seconds: without it every token-authenticated request runs a token, a user and two
permission queries (~2 ms).

Changes made in this process (a token revoked, a user deactivated, a role changed, in the
admin or a management command) drop the entries at once, through signals; a change made by
another process takes effect within TOKEN_CACHE_TTL.
"""
from __future__ import annotations

import threading
import time
from collections import OrderedDict
from datetime import datetime
from typing import Callable

from django.contrib.auth import get_user_model
from django.contrib.auth.models import Group, Permission
from django.db import transaction
from django.db.models.signals import m2m_changed, post_delete, post_save

from lifecycle_site.api.models import ApiToken

TOKEN_CACHE_TTL = 5.0
TOKEN_CACHE_SIZE = 256
# A token's last_used is written at most this often (it tells an admin which tokens are in use).
LAST_USED_EVERY_S = 60


class _Grant:
    """A token's user, as loaded, and what the user may do."""

    __slots__ = ("expires", "token_id", "user_id", "db", "user_values", "is_active", "permissions", "last_used",
                 "directory", "vouched")

    def __init__(self, record: ApiToken) -> None:
        user = record.user
        self.expires = time.monotonic() + TOKEN_CACHE_TTL
        self.token_id = record.pk
        self.user_id = user.pk
        self.db = user._state.db
        self.user_values = tuple(getattr(user, f.attname) for f in user._meta.concrete_fields)
        self.is_active = user.is_active
        # Every backend's answer for an active user (none for an inactive one).
        self.permissions = frozenset(user.get_all_permissions()) if user.is_active else frozenset()
        self.last_used: datetime | None = record.last_used
        # A company directory's account (sign_in): its source ("" for a local account), and when the
        # directory last vouched for it (a sign-in, or a lookup): its tokens work for a while after.
        account = getattr(user, "directory_account", None)
        self.directory: str = account.source if account is not None else ""
        self.vouched: datetime | None = account.vouched if account is not None else None

    def user(self):
        """A fresh user object per request, its permissions filled in (has_perm asks no query)."""
        user = get_user_model().from_db(self.db, None, self.user_values)
        user._perm_cache = set(self.permissions)
        return user


_grants: OrderedDict[str, _Grant] = OrderedDict()  # token digest -> grant, oldest use first
_grants_lock = threading.Lock()
_generation = 0  # counts invalidations, so a grant read before one is not stored after it


def cached(digest: str) -> _Grant | None:
    with _grants_lock:
        grant = _grants.get(digest)
        if grant is None:
            return None
        if time.monotonic() >= grant.expires:
            del _grants[digest]
            return None
        _grants.move_to_end(digest)
        return grant


def load(digest: str) -> _Grant | None:
    generation = _generation
    record = ApiToken.objects.select_related("user", "user__directory_account").filter(digest=digest).first()
    if record is None:
        return None  # unknown tokens are not kept: nothing to gain, and they would crowd out real ones
    grant = _Grant(record)
    with _grants_lock:
        if generation == _generation:
            _grants[digest] = grant
            _grants.move_to_end(digest)
            while len(_grants) > TOKEN_CACHE_SIZE:
                _grants.popitem(last=False)
    return grant


def forget(match: Callable[[str, _Grant], bool] | None = None) -> None:
    """Drop the kept grants (those ``match`` selects, or all) and any being loaded now."""
    global _generation
    with _grants_lock:
        _generation += 1
        if match is None:
            _grants.clear()
        else:
            for digest in [d for d, g in _grants.items() if match(d, g)]:
                del _grants[digest]


def _forget_now_and_at_commit(using: str | None, match: Callable[[str, _Grant], bool] | None = None) -> None:
    # Signals fire before the change is committed: a request could still read, and keep, the
    # old rows in between. Forgetting again once it is committed closes that gap.
    forget(match)
    transaction.on_commit(lambda: forget(match), using=using)


def _token_changed(sender, instance: ApiToken, using=None, **kwargs) -> None:
    token_digest, token_id = instance.digest, instance.pk  # a deleted instance loses its pk later
    _forget_now_and_at_commit(using, lambda digest, grant: digest == token_digest or grant.token_id == token_id)


def _user_changed(sender, instance, using=None, **kwargs) -> None:
    user_id = instance.pk
    _forget_now_and_at_commit(using, lambda digest, grant: grant.user_id == user_id)


def _roles_changed(sender, using=None, **kwargs) -> None:
    _forget_now_and_at_commit(using)


def connect_invalidation() -> None:
    """Called once, from the app's ready()."""
    user_model = get_user_model()
    for signal, done in ((post_save, "saved"), (post_delete, "deleted")):
        signal.connect(_token_changed, sender=ApiToken, dispatch_uid=f"api_grants_token_{done}")
        signal.connect(_user_changed, sender=user_model, dispatch_uid=f"api_grants_user_{done}")
    for model in (Group, Permission):  # deleting either removes memberships without m2m signals
        post_delete.connect(_roles_changed, sender=model, dispatch_uid=f"api_grants_{model.__name__}_deleted")
    for through in (user_model.groups.through, user_model.user_permissions.through, Group.permissions.through):
        m2m_changed.connect(_roles_changed, sender=through, dispatch_uid=f"api_grants_{through.__name__}")
