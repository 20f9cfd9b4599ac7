"""Asking the LDAP directory about an account whose API token is used, now and then: a token
works without a sign-in, so without this a person removed from the directory, switched off there
or moved out of the mapped group kept the role of their last sign-in (up to
LIFECYCLE_DIRECTORY_TOKEN_DAYS). Needs the service account (LIFECYCLE_LDAP_BIND_USER): the
user's own password is not at hand. An OpenID provider offers no such lookup.

At most every CHECK_EVERY_S per account (and per site process); a directory that cannot be
asked changes nothing (the token keeps the role it had, within its days) and is asked again
after RETRY_AFTER_S. Each lookup is bounded like a sign-in's (LIFECYCLE_LDAP_TIMEOUT).
"""
from __future__ import annotations

import logging
import threading
import time
from datetime import datetime

from django.conf import settings
from django.utils import timezone
from django_python3_ldap import ldap as library
from ldap3.core.exceptions import LDAPException

from lifecycle_site.sign_in import accounts, ldap
from lifecycle_site.sign_in.models import DirectoryAccount

log = logging.getLogger("lifecycle.sign_in")

CHECK_EVERY_S = 15 * 60.0
RETRY_AFTER_S = 60.0
AD_ACCOUNT_DISABLED = 0x2  # Active Directory's userAccountControl flag

_lock = threading.Lock()
_not_before: dict[int, float] = {}  # user id -> when (monotonic) this process may ask again


class Gone(Exception):
    """The directory no longer has the account, or has it switched off: it was switched off here."""

    def __init__(self, username: str, why: str) -> None:
        super().__init__(f"directory account {username} {why}")
        self.username, self.why = username, why


def due(user_id: int, source: str, vouched: datetime | None) -> bool:
    """Whether the directory is to be asked about this account before its token is taken."""
    if source != DirectoryAccount.LDAP or not getattr(settings, "LDAP_ON", False) \
            or not getattr(settings, "LDAP_AUTH_CONNECTION_USERNAME", None):
        return False
    with _lock:
        if time.monotonic() < _not_before.get(user_id, 0.0):
            return False
    return vouched is None or (timezone.now() - vouched).total_seconds() > CHECK_EVERY_S


def check(user_id: int) -> None:
    """Ask the directory: the account's role follows its groups (none without a mapped group);
    raises Gone for an account the directory no longer has or has switched off."""
    with _lock:  # one lookup at a time per account, also while this one runs
        _not_before[user_id] = time.monotonic() + RETRY_AFTER_S
    account = DirectoryAccount.objects.select_related("user").get(user_id=user_id)
    user = account.user
    try:
        with library.connection() as connection:  # bound as the service account
            if connection is None:
                raise LDAPException("the service account's bind failed")
            entry = connection._connection.response[0] if connection.has_user(username=account.subject) else None
            if entry is not None:
                attributes = entry.get("attributes") or {}
                if not _disabled(attributes):
                    groups = ldap.groups_of(connection._connection, str(entry["dn"]), attributes)
    except (LDAPException, ldap.Refused) as error:
        log.warning("company directory not asked about %s (its token keeps its role for now): %s",
                    user.get_username(), error)
        return
    if entry is None or _disabled(attributes):
        why = "is no longer in the directory" if entry is None else "is switched off in the directory"
        user.is_active = False
        user.save(update_fields=["is_active"])  # (its tokens' grants are forgotten: api/grants.py)
        log.warning("directory account %s %s: switched off here too", user.get_username(), why)
        raise Gone(user.get_username(), why)
    role = accounts.role_for(groups, settings.LIFECYCLE_LDAP_ROLES)
    if role != (account.role or None):
        log.warning("directory account %s: role %s -> %s (its groups: %s)", user.get_username(),
                    account.role or "none", role or "none", ", ".join(groups) or "none")
    accounts.confirmed(user, role, groups)
    with _lock:
        _not_before[user_id] = time.monotonic() + CHECK_EVERY_S


def _disabled(attributes: dict) -> bool:
    value = attributes.get("userAccountControl")
    value = value[0] if isinstance(value, list) and value else value
    try:
        return bool(int(value) & AD_ACCOUNT_DISABLED)
    except (TypeError, ValueError):
        return False


def forget() -> None:
    """Ask again at the next use (tests)."""
    with _lock:
        _not_before.clear()
