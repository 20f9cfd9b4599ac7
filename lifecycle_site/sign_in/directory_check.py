"""Asking the LDAP directory about an account whose API token is used, now and then: a token
works without a sign-in, so without this a person removed from the directory, switched off there
or moved out of the mapped group kept the role of their last sign-in (up to
LIFECYCLE_DIRECTORY_TOKEN_DAYS). Needs the service account (LIFECYCLE_LDAP_BIND_USER): the
user's own password is not at hand. An OpenID provider offers no such lookup.

At most every CHECK_EVERY_S per account (and per site process); a directory that cannot be
asked changes nothing (the token keeps the role it had, within its days) and is asked again
after RETRY_AFTER_S. Each step of a lookup (connect, binds, searches) is bounded like a
sign-in's, by LIFECYCLE_LDAP_TIMEOUT.
"""
from __future__ import annotations

import logging
import threading
import time
from datetime import datetime

import ldap3
from django.conf import settings
from django.utils import timezone
from django_python3_ldap import ldap as library
from django_python3_ldap.utils import format_search_filter
from ldap3.core.exceptions import LDAPException

from lifecycle_site.sign_in import accounts, ldap, problems
from lifecycle_site.sign_in.models import DirectoryAccount

log = logging.getLogger("lifecycle.sign_in")

CHECK_EVERY_S = 15 * 60.0
RETRY_AFTER_S = 60.0
AD_ACCOUNT_DISABLED = 0x2  # Active Directory's userAccountControl flag

_lock = threading.Lock()
_not_before: dict[int, float] = {}  # user id -> when (monotonic) this process may ask again


class Gone(Exception):
    """The directory said plainly that it no longer has the account, or has it switched off: the
    account lost its role and its directory's word, so its tokens are refused until it signs in
    again (which the directory must allow). Not switched off here: a directory answer read wrong
    (a user base moved, say) is then mended by a sign-in, not by an admin for every account."""

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
    return vouched is not None and (timezone.now() - vouched).total_seconds() > CHECK_EVERY_S


def check(user_id: int) -> None:
    """Ask the directory: the account's role follows its groups (none without a mapped group,
    and then no confirmation either); raises Gone when the directory says it has no such account
    or has it switched off. Anything else (unreachable, refused, an answer it could not make
    plain) changes nothing."""
    with _lock:  # one lookup at a time per account, also while this one runs
        _not_before[user_id] = time.monotonic() + RETRY_AFTER_S
    account = DirectoryAccount.objects.select_related("user").get(user_id=user_id)
    user = account.user
    try:
        with library.connection() as connection:  # bound as the service account
            if connection is None:
                raise ldap.Refused(problems.DIRECTORY_UNREACHABLE)
            found = _lookup(connection._connection, account.subject)
            groups = [] if found in (None, DISABLED) else ldap.groups_of(connection._connection, *found)
    except (LDAPException, ldap.Refused) as error:
        log.warning("company directory not asked about %s (its token keeps its role for now): %s",
                    user.get_username(), error)
        return
    if found in (None, DISABLED):
        why = "is no longer in the directory" if found is None else "is switched off in the directory"
        accounts.disowned(user)
        log.warning("directory account %s %s: its role and its tokens are withdrawn until it signs in again",
                    user.get_username(), why)
        raise Gone(user.get_username(), why)
    role = accounts.role_for(groups, settings.LIFECYCLE_LDAP_ROLES)
    if role != (account.role or None):
        log.warning("directory account %s: role %s -> %s (its groups: %s)", user.get_username(),
                    account.role or "none", role or "none", ", ".join(groups) or "none")
    accounts.confirmed(user, role, groups)
    with _lock:
        _not_before[user_id] = time.monotonic() + CHECK_EVERY_S


DISABLED = ("", {})  # _lookup's answer for an account the directory has switched off


def _lookup(connection, username: str) -> tuple[str, dict] | None:
    """(DN, attributes) of the user, DISABLED, or None when the directory answered plainly that
    there is none (no entry, no referral, the search complete). Raises Refused for anything it
    cannot make plain: an error, a referral elsewhere, a search cut short, an entry unreadable."""
    try:
        connection.search(search_base=settings.LDAP_AUTH_SEARCH_BASE, search_filter=format_search_filter(
            {"username": username}), search_scope=ldap3.SUBTREE, attributes=ldap3.ALL_ATTRIBUTES,
            get_operational_attributes=True, size_limit=2)
    except LDAPException as error:  # (raised out of the library's connection(), which cannot take it)
        raise ldap.Refused(problems.DIRECTORY_UNREACHABLE) from error
    response = connection.response or []
    entries = [r for r in response if r.get("type") == "searchResEntry"]
    result = (connection.result or {}).get("result")
    if not entries:
        if result == 0 and not response:  # success, nothing found, nothing referred
            return None
        raise ldap.Refused(problems.DIRECTORY_UNREACHABLE)
    attributes = entries[0].get("attributes") or {}
    if not attributes:  # found, but not readable by the service account
        raise ldap.Refused(problems.DIRECTORY_UNREACHABLE)
    return DISABLED if _disabled(attributes) else (str(entries[0].get("dn")), attributes)


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
