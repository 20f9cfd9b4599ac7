"""``manage.py create_api_token USERNAME``: print a new bearer token for the JSON API."""
from __future__ import annotations

from django.contrib.auth import get_user_model
from django.core.management.base import BaseCommand, CommandError
from django.utils.translation import gettext as _
from django.utils.translation import gettext_lazy

from lifecycle_site.api.models import ApiToken, TooManyTokens
from lifecycle_site.languages.cli import InCliLanguage


class Command(InCliLanguage, BaseCommand):  # in the CLI's language: languages/cli.py
    help = gettext_lazy("Create an API token for a user and print it (it is shown only this once).")

    def add_arguments(self, parser) -> None:
        parser.add_argument("username")
        parser.add_argument("--name", default="", help=_("What the token is for, e.g. 'CI bring-up'"))

    def handle(self, *args, username: str, name: str, **options) -> None:
        user = get_user_model().objects.filter(username=username).first()
        if user is None:
            raise CommandError(_("There is no user %(user)s; create one with 'manage.py createsuperuser'.") % {
                "user": repr(username)})
        try:
            # On record without an account: whoever has a shell on the site made it.
            _record, token = ApiToken.issue(user, name, by=None, via="command line")  # (on record: in English)
        except TooManyTokens as exc:
            raise CommandError(str(exc)) from None
        # Only the token on stdout, so scripts can capture it: TOKEN=$(manage.py create_api_token ci)
        self.stdout.write(token)
        self.stderr.write(
            _("Token for %(user)s created; it cannot be shown again. Send it as 'Authorization: Bearer <token>'.") % {
                "user": username}
        )
