"""django-axes' database handler, with a narrower reset on a successful login.

With AXES_LOCKOUT_PARAMETERS = ["username", "ip_address"], axes' AXES_RESET_ON_SUCCESS deletes
every attempt of the account *or* of the address: a good login of one's own account wiped the
failures counted against any other account tried from the same address, so an account holder
could guess another account's password without end (4 guesses, a good login, repeat). axes has
no setting for a narrower reset (its maintainers suggest the account and address combination,
jazzband/django-axes#317), so this handler resets only that.
"""
from __future__ import annotations

from axes.handlers.database import AxesDatabaseHandler
from axes.helpers import get_client_username
from axes.models import AccessAttempt
from django.http import HttpRequest


class LoginAttempts(AxesDatabaseHandler):
    def reset_user_attempts(self, request: HttpRequest, credentials: dict | None = None) -> int:
        """After a good login: forget the failures of this account from this address, and no others.

        The user's own mistypes are gone, so they are not left one typo from a block (neither for
        the account nor for their address). Failures against other accounts from this address, and
        against this account from other addresses (someone else guessing it), still count."""
        username = get_client_username(request, credentials)
        count, _ = AccessAttempt.objects.filter(username=username, ip_address=request.axes_ip_address).delete()
        return count
