"""Bearer tokens for automation. Only a hash is stored; the token is shown once.

Like a personal access token: it acts as its user, so it never grants more than the user
has (a role taken away is taken from the token too). Any logged-in user may make and revoke
their own (the "API tokens" page); admins may revoke anyone's. Each creation and revocation
is on record (TokenEvent: who, for whom, when, where), for admins to review.
"""
from __future__ import annotations

import hashlib
import secrets

from django.conf import settings
from django.db import models, transaction
from django.db.models.signals import pre_delete
from django.utils.translation import gettext as _
from django.utils.translation import gettext_lazy

TOKEN_PREFIX = "lcm_"
MAX_TOKENS_PER_USER = 20


def hash_token(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


class TooManyTokens(Exception):
    """The user has MAX_TOKENS_PER_USER tokens already."""

    @classmethod
    def of(cls, user) -> "TooManyTokens":
        return cls(_("%(user)s has %(most)s tokens already, the most one account may have: revoke one that is no "
                     "longer used first.") % {"user": user.get_username(), "most": MAX_TOKENS_PER_USER})


class ApiToken(models.Model):
    user = models.ForeignKey(settings.AUTH_USER_MODEL, verbose_name=gettext_lazy("user"), on_delete=models.CASCADE,
                             related_name="api_tokens")
    name = models.CharField(gettext_lazy("name"), max_length=100, blank=True,
                            help_text=gettext_lazy("What the token is for."))
    digest = models.CharField(gettext_lazy("digest"), max_length=64, unique=True, editable=False)
    hint = models.CharField(gettext_lazy("hint"), max_length=12, editable=False,
                            help_text=gettext_lazy("First characters, to tell tokens apart."))
    created = models.DateTimeField(gettext_lazy("created"), auto_now_add=True)
    last_used = models.DateTimeField(gettext_lazy("last used"), null=True, blank=True)

    class Meta:
        ordering = ["-created"]
        verbose_name = gettext_lazy("api token")
        verbose_name_plural = gettext_lazy("api tokens")

    def __str__(self) -> str:
        return f"{self.hint}… ({self.user})"

    @classmethod
    def issue(cls, user, name: str = "", *, by=None, via: str = "") -> tuple["ApiToken", str]:
        """Create a token for ``user``, made by ``by`` (None: no account, e.g. on the command
        line) through ``via``; returns the record and the clear-text token, kept nowhere."""
        if cls.objects.filter(user=user).count() >= MAX_TOKENS_PER_USER:
            raise TooManyTokens.of(user)
        token = TOKEN_PREFIX + secrets.token_urlsafe(32)
        with transaction.atomic():
            record = cls.objects.create(user=user, name=name, digest=hash_token(token), hint=token[:10])
            TokenEvent.note(TokenEvent.CREATED, record, by, via)
        return record, token

    def revoke(self, *, by, via: str = "") -> None:
        """Delete the token (it stops working at once in this process, within seconds in the
        others: api/grants.py) and put that on record."""
        with transaction.atomic():
            TokenEvent.note(TokenEvent.REVOKED, self, by, via)
            self.noted = True  # for _token_deleted: on record already
            self.delete()


class TokenEvent(models.Model):
    """A token made or revoked. Append-only, like the audit records."""

    CREATED, REVOKED = "created", "revoked"

    at = models.DateTimeField(gettext_lazy("at"), auto_now_add=True, db_index=True)
    action = models.CharField(gettext_lazy("action"), max_length=8, choices=[(CREATED, gettext_lazy("created")),
                                                     (REVOKED, gettext_lazy("revoked"))])
    hint = models.CharField(gettext_lazy("token"), max_length=12,
                            help_text=gettext_lazy("The token's first characters."))
    token_name = models.CharField(gettext_lazy("token name"), max_length=100, blank=True)
    owner = models.ForeignKey(settings.AUTH_USER_MODEL, verbose_name=gettext_lazy("owner"), null=True, blank=True,
                              on_delete=models.SET_NULL, related_name="+")
    owner_name = models.CharField(gettext_lazy("token of"), max_length=150)
    actor = models.ForeignKey(settings.AUTH_USER_MODEL, verbose_name=gettext_lazy("actor"), null=True, blank=True,
                              on_delete=models.SET_NULL, related_name="+")
    actor_name = models.CharField(gettext_lazy("by"), max_length=150, blank=True)
    via = models.CharField(gettext_lazy("via"), max_length=32, blank=True,
                           help_text=gettext_lazy("admin, the API tokens page, the command line"))

    class Meta:
        ordering = ["-at", "-id"]
        verbose_name = gettext_lazy("token event")
        verbose_name_plural = gettext_lazy("token events")

    def __str__(self) -> str:
        return _("%(hint)s… %(action)s by %(actor)s") % {
            "hint": self.hint, "action": self.get_action_display(), "actor": self.actor_name or "?"}

    def save(self, *args, **kwargs) -> None:
        if self.pk is not None:
            raise ValueError("Token events cannot be changed.")
        super().save(*args, **kwargs)

    @classmethod
    def note(cls, action: str, token: ApiToken, actor, via: str, owner_deleted: bool = False) -> "TokenEvent":
        """``owner_deleted``: the owner's row goes in the same transaction, so the event names
        the owner only by name (a reference would point at a deleted row)."""
        return cls.objects.create(
            action=action, hint=token.hint, token_name=token.name, owner=None if owner_deleted else token.user,
            owner_name=token.user.get_username(), actor=actor if getattr(actor, "pk", None) else None,
            actor_name=actor.get_username() if getattr(actor, "pk", None) else "", via=via,
        )


# Deleted with its user (the admin's delete, a script's): no token leaves without a record.
DELETED_WITH_USER = "deleted with its user"


def _token_deleted(sender, instance: ApiToken, **kwargs) -> None:
    if getattr(instance, "noted", False):
        return
    TokenEvent.note(TokenEvent.REVOKED, instance, None, DELETED_WITH_USER, owner_deleted=True)


pre_delete.connect(_token_deleted, sender=ApiToken, dispatch_uid="api.token_deleted")
