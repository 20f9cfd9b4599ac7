"""``manage.py create_api_token USERNAME``: print a new bearer token for the JSON API."""
from __future__ import annotations

from django.contrib.auth import get_user_model
from django.core.management.base import BaseCommand, CommandError

from lifecycle_site.api.models import ApiToken, TooManyTokens


class Command(BaseCommand):
    help = "Create an API token for a user and print it (it is shown only this once)."

    def add_arguments(self, parser) -> None:
        parser.add_argument("username")
        parser.add_argument("--name", default="", help="What the token is for, e.g. 'CI bring-up'")

    def handle(self, *args, username: str, name: str, **options) -> None:
        user = get_user_model().objects.filter(username=username).first()
        if user is None:
            raise CommandError(f"There is no user {username!r}; create one with 'manage.py createsuperuser'.")
        try:
            # On record without an account: whoever has a shell on the site made it.
            _, token = ApiToken.issue(user, name, by=None, via="command line")
        except TooManyTokens as exc:
            raise CommandError(str(exc)) from None
        # Only the token on stdout, so scripts can capture it: TOKEN=$(manage.py create_api_token ci)
        self.stdout.write(token)
        self.stderr.write(
            f"Token for {username} created; it cannot be shown again. Send it as 'Authorization: Bearer <token>'."
        )
