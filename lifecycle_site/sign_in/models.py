"""Which accounts came from the company directory, and as whom.

A local account (made in the admin, with a password) never becomes a directory account: an
LDAP or OIDC login whose name matches a local account is refused, so the directory cannot take
over ``admin``. An OIDC account is found again by the provider's subject, not by e-mail or name
(both can change or be reused)."""
from __future__ import annotations

from django.conf import settings
from django.db import models
from django.utils.translation import gettext_lazy, pgettext_lazy


class DirectoryAccount(models.Model):
    LDAP = "ldap"
    OIDC = "oidc"
    SOURCES = [(LDAP, "LDAP / Active Directory"), (OIDC, "OpenID Connect")]

    user = models.OneToOneField(settings.AUTH_USER_MODEL, verbose_name=gettext_lazy("user"), on_delete=models.CASCADE,
                                related_name="directory_account")
    source = models.CharField(gettext_lazy("source"), max_length=8, choices=SOURCES)
    subject = models.CharField(pgettext_lazy("directory account", "subject"), max_length=255,
                               help_text=gettext_lazy("the provider's 'sub', or the directory's user name"))
    role = models.CharField(gettext_lazy("role"), max_length=16, blank=True,
                            help_text=gettext_lazy("the role its groups gave at the last sign-in"))
    groups = models.TextField(
        gettext_lazy("groups"), blank=True,
        help_text=gettext_lazy("the groups it had at the last sign-in (at most 2,000 characters)")
    )
    last_sign_in = models.DateTimeField(gettext_lazy("last sign in"), null=True, blank=True)
    confirmed = models.DateTimeField(
        gettext_lazy("confirmed by the directory"), null=True, blank=True,
        help_text=gettext_lazy("when the directory last confirmed the account and its role without a sign-in "
                               "(LDAP, when one of its API tokens is used)"))

    class Meta:
        constraints = [models.UniqueConstraint(fields=["source", "subject"], name="one_account_per_directory_subject")]
        verbose_name = gettext_lazy("directory account")
        verbose_name_plural = gettext_lazy("directory accounts")

    @property
    def vouched(self):
        """When the directory last vouched for the account: its last sign-in or its last
        confirmation, whichever is later (None for neither); its API tokens count their days from it."""
        return max((m for m in (self.last_sign_in, self.confirmed) if m), default=None)

    def __str__(self) -> str:
        return f"{self.user} ({self.get_source_display()})"
