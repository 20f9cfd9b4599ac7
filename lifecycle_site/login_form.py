"""The login form: after a wrong password the keyboard goes to the password field (the user
name is kept), not back to the user name, where Django's form puts it."""
from __future__ import annotations

from django.contrib.auth.forms import AuthenticationForm
from django.core.exceptions import ValidationError


class LoginForm(AuthenticationForm):
    def clean(self) -> dict:
        try:
            return super().clean()
        except ValidationError:  # the name and password did not match (or the account is inactive)
            self.fields["username"].widget.attrs.pop("autofocus", None)
            self.fields["password"].widget.attrs["autofocus"] = True
            raise
