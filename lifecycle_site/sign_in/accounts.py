"""A directory user's account here: refused for local names, its role from its groups at every
sign-in (a group removed in the directory takes the role away at the next one), its session
bounded so that the next one comes."""
from __future__ import annotations

from collections.abc import Iterable
from datetime import timedelta

from django.conf import settings
from django.contrib.auth import get_user_model
from django.contrib.auth.models import AbstractBaseUser, Group
from django.db import transaction
from django.utils import timezone

from lifecycle_site.fleet.roles import ROLES
from lifecycle_site.sign_in.config import ROLE_ORDER
from lifecycle_site.sign_in.models import DirectoryAccount

GROUPS_KEPT = 2000  # characters of the group list kept for the admin to see
MAX_GROUPS = 500  # groups read per user: a directory's answer is bounded like any other input


def fitted(field: str, value: object) -> str:
    """A directory's value for a user field, cut to what the user table holds (the model says)."""
    return str(value)[:get_user_model()._meta.get_field(field).max_length]


def role_for(groups: Iterable[str], mapping: dict[str, str]) -> str | None:
    """The highest role any of ``groups`` maps to (names compared in lower case), or None."""
    roles = {mapping.get(str(group).strip().lower()) for group in groups}
    return max((r for r in roles if r), key=ROLE_ORDER.index, default=None)


def is_local(username: str) -> bool:
    """Whether ``username`` belongs to an account that did not come from the directory."""
    return get_user_model().objects.filter(username=username, directory_account__isnull=True).exists()


def user_of(source: str, subject: str) -> AbstractBaseUser | None:
    account = DirectoryAccount.objects.select_related("user").filter(source=source, subject=subject).first()
    return account.user if account is not None else None


@transaction.atomic
def signed_in(user: AbstractBaseUser, source: str, subject: str, role: str, groups: Iterable[str]) -> None:
    """Record the sign-in and give ``user`` exactly ``role`` among the product's roles (its other
    groups stay). admins_are_staff (fleet/roles.py) follows the admin role with the staff flag."""
    DirectoryAccount.objects.update_or_create(
        user=user, defaults={"source": source, "subject": subject, "role": role, "groups": _listed(groups),
                             "last_sign_in": timezone.now()})
    _give_role(user, role)


@transaction.atomic
def confirmed(user: AbstractBaseUser, role: str | None, groups: Iterable[str]) -> None:
    """The directory answered for the account without a sign-in (sign_in.directory_check): its
    role is now ``role``. None (no mapped group any more): no role, and no confirmation either
    (sign-in would refuse it), so its tokens' days keep counting from before."""
    changes = {"role": role or "", "groups": _listed(groups)}
    if role is not None:
        changes["confirmed"] = timezone.now()
    DirectoryAccount.objects.filter(user=user).update(**changes)
    _give_role(user, role)


@transaction.atomic
def disowned(user: AbstractBaseUser) -> None:
    """The directory no longer has the account, or has it switched off: no role, and nothing the
    directory vouches for, so its tokens are refused until it signs in again."""
    DirectoryAccount.objects.filter(user=user).update(role="", last_sign_in=None, confirmed=None)
    _give_role(user, None)


def _listed(groups: Iterable[str]) -> str:
    return ", ".join(sorted(str(g) for g in groups))[:GROUPS_KEPT]


def _give_role(user: AbstractBaseUser, role: str | None) -> None:
    others = list(user.groups.filter(name__in=[r for r in ROLES if r != role]))
    if others:
        user.groups.remove(*others)
    if role is not None:
        wanted = Group.objects.get(name=role)
        if not user.groups.filter(pk=wanted.pk).exists():
            user.groups.add(wanted)


def bound_session(sender, request, user, **kwargs) -> None:
    """user_logged_in: a directory account's session ends LIFECYCLE_DIRECTORY_SESSION_HOURS after
    the sign-in, however active (a fixed end, not an idle one: the role must be read again)."""
    if request is None or not hasattr(request, "session") or not DirectoryAccount.objects.filter(user=user).exists():
        return
    request.session.set_expiry(timezone.now() + timedelta(hours=settings.LIFECYCLE_DIRECTORY_SESSION_HOURS))
