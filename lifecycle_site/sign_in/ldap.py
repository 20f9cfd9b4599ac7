"""Sign-in with the company's LDAP directory or Active Directory (django-python3-ldap on ldap3,
pure Python: nothing to compile on an edge device). The library binds as the user, reads the
user's entry and creates or updates the account; this module adds what a plant needs:

- a local account's name is never taken over by the directory (``clean_user_data``);
- the role comes from the user's groups at every sign-in, and no mapped group means no login
  (``give_role``, which searches the groups that name the user as ``member``, and the groups
  that name those, as Active Directory nests them);
- a directory that cannot be reached is told apart from a wrong password (``Backend``).
"""
from __future__ import annotations

import logging

import ldap3
from django.conf import settings
from django.db import transaction
from django.http import HttpRequest
from django_python3_ldap import ldap as library
from django_python3_ldap.auth import LDAPBackend
from django_python3_ldap.utils import import_func
from ldap3.core.exceptions import LDAPException
from ldap3.utils.conv import escape_filter_chars

from lifecycle_site.sign_in import accounts, problems
from lifecycle_site.sign_in.models import DirectoryAccount

log = logging.getLogger("lifecycle.sign_in")


class Refused(Exception):
    def __init__(self, problem: problems.Problem) -> None:
        super().__init__(problem.code)
        self.problem = problem


def clean_user_data(fields: dict) -> dict:
    """LDAP_AUTH_CLEAN_USER_DATA: before the library writes the account. Refuses a name that
    belongs to a local account (the directory's spelling, which may differ in case from what was
    typed), and cuts the directory's values to what the user table holds."""
    fields = {name: accounts.fitted(name, value) for name, value in fields.items()}
    if accounts.is_local(fields.get("username", "")):
        raise Refused(problems.LOCAL_NAME)
    return fields


def bind_name(fields: dict) -> str:
    """LDAP_AUTH_FORMAT_USERNAME: the name a user binds with (``uid=NAME,USER_BASE``, or
    ``NAME@DOMAIN`` for Active Directory). The service account (LIFECYCLE_LDAP_BIND_USER), which
    the library passes through the same function, binds as it is set when that is a DN or
    NAME@DOMAIN, as the settings describe it (formed like a user's, a DN became
    ``uid=cn\\3Dlookup...``: its bind failed, and so did every sign-in, as a wrong password)."""
    service = settings.LDAP_AUTH_CONNECTION_USERNAME
    name = next(iter(fields.values()), None) if len(fields) == 1 else None
    if service and name == service and ("=" in service or "@" in service):
        return service
    return import_func(settings.SIGN_IN_LDAP_USER_FORMAT)(fields)


# Levels of groups within groups followed: Active Directory's usual nesting (AGDLP: a user in a
# global group, that one in the domain local group that is mapped) is two.
NESTING_DEPTH = 8
MEMBERS_PER_SEARCH = 50  # member DNs named in one search filter


def groups_of(connection: ldap3.Connection, dn: str, attributes: dict) -> list[str]:
    """The names (cn) and DNs of the groups that list ``dn`` as a member, plus any memberOf, and
    the groups that list those, NESTING_DEPTH levels up (a loop of groups ends: each is read once)."""
    member_of = [str(g) for g in (attributes.get("memberOf") or [])][:accounts.MAX_GROUPS]
    groups: dict[str, list[str]] = {g.lower(): [g] for g in member_of}  # group DN (lower case) -> DN and cns
    level = [dn, *member_of]
    for _ in range(NESTING_DEPTH + 1):
        found = _groups_listing(connection, level, room=accounts.MAX_GROUPS - len(groups))
        level = [group_dn for group_dn in found if group_dn.lower() not in groups]
        groups.update({group_dn.lower(): [group_dn, *found[group_dn]] for group_dn in level})
        if not level or len(groups) >= accounts.MAX_GROUPS:
            break
    names = {name for dn_and_cns in groups.values() for name in dn_and_cns}
    for group_dn in list(names):  # "cn=operators,ou=groups,..." also counts as "operators"
        first = group_dn.split(",", 1)[0]
        if first.lower().startswith("cn="):
            names.add(first[3:])
    return sorted(names)


def _groups_listing(connection: ldap3.Connection, members: list[str], room: int) -> dict[str, list[str]]:
    """The groups under the group base that list any of ``members`` as a member: DN -> its cns
    (at most ``room`` of them)."""
    found: dict[str, list[str]] = {}
    for start in range(0, len(members), MEMBERS_PER_SEARCH):
        if len(found) >= room:
            break
        terms = "".join(f"(member={escape_filter_chars(m)})" for m in members[start:start + MEMBERS_PER_SEARCH])
        try:
            connection.search(search_base=settings.LIFECYCLE_LDAP_GROUP_BASE, search_filter=f"(|{terms})",
                              search_scope=ldap3.SUBTREE, attributes=["cn"], size_limit=accounts.MAX_GROUPS)
        except LDAPException as error:  # raised out of the library's connection(), which re-yields on its own errors
            log.warning("company directory: the groups of %s could not be read: %s", members[0], error)
            raise Refused(problems.DIRECTORY_UNREACHABLE) from error
        for entry in connection.response or []:
            if entry.get("type") == "searchResEntry" and entry.get("dn") and len(found) < room:
                found[str(entry["dn"])] = [str(cn) for cn in (entry.get("attributes", {}).get("cn") or [])]
    return found


def give_role(user, attributes: dict, *, connection: ldap3.Connection, dn: str) -> None:
    """LDAP_AUTH_SYNC_USER_RELATIONS: the role from the groups, or no login at all."""
    groups = groups_of(connection, dn, attributes)
    role = accounts.role_for(groups, settings.LIFECYCLE_LDAP_ROLES)
    if role is None:
        log.warning("directory user %s has no mapped group (groups: %s)", user.username, ", ".join(groups) or "none")
        raise Refused(problems.NO_ROLE)
    accounts.signed_in(user, DirectoryAccount.LDAP, user.username, role, groups)


def reachable() -> bool:
    """Whether one of the directory's servers answers with TLS (anonymously, no password sent)."""
    for url in settings.LDAP_AUTH_URL:
        server_args = dict(settings.LDAP_AUTH_CONNECT_ARGS, connect_timeout=settings.LDAP_AUTH_CONNECT_TIMEOUT,
                           get_info=ldap3.NONE, use_ssl=settings.LDAP_AUTH_CONNECT_USE_SSL)
        if settings.LDAP_AUTH_USE_TLS:
            server_args["tls"] = ldap3.Tls(**settings.LDAP_AUTH_TLS_ARGS)
        connection = ldap3.Connection(ldap3.Server(url, **server_args), raise_exceptions=True,
                                      receive_timeout=settings.LDAP_AUTH_RECEIVE_TIMEOUT)
        try:
            connection.open()
            if settings.LDAP_AUTH_USE_TLS:
                connection.start_tls(read_server_info=False)
            return True
        except LDAPException as error:
            log.warning("company directory %s not usable: %s", url, error)
        finally:
            try:
                connection.unbind()
            except LDAPException:  # nothing left to close
                pass
    return False


class Backend(LDAPBackend):
    """Tried after the local accounts (AUTHENTICATION_BACKENDS)."""

    def authenticate(self, request: HttpRequest | None, username: str | None = None, password: str | None = None,
                     **kwargs):
        if not username or not password or accounts.is_local(username):
            return None  # not a directory sign-in, or a local account's (ModelBackend answered)
        try:
            with transaction.atomic():  # a refusal in give_role takes back the account just made
                user = library.authenticate(username=username, password=password)
        except Refused as refusal:
            problems.note(request, refusal.problem)
            return None
        except LDAPException as error:  # the library's closing unbind fails on a socket TLS already closed
            log.warning("company directory not usable for the sign-in of %s: %s", username, error)
            problems.note(request, problems.DIRECTORY_UNREACHABLE)
            return None
        if user is None:
            if not reachable():
                problems.note(request, problems.DIRECTORY_UNREACHABLE)
            return None
        return user if self.user_can_authenticate(user) else None

    async def aauthenticate(self, request, **kwargs):  # no async login path here; keep the same rules
        from asgiref.sync import sync_to_async

        return await sync_to_async(self.authenticate)(request, **kwargs)
