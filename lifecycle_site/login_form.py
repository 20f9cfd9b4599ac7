"""The login form: after a wrong password the keyboard goes to the password field (the user
name is kept), not back to the user name, where Django's form puts it. When the company
directory refused for a reason of its own (unreachable, no role mapped), it says that reason."""
from __future__ import annotations

from django.contrib.auth.forms import AuthenticationForm
from django.core.exceptions import ValidationError

from lifecycle_site.sign_in import problems


class LoginForm(AuthenticationForm):
    sign_in_problem: problems.Problem | None = None

    def clean(self) -> dict:
        try:
            return super().clean()
        except ValidationError:  # the name and password did not match (or the account is inactive)
            self.fields["username"].widget.attrs.pop("autofocus", None)
            self.fields["password"].widget.attrs["autofocus"] = True
            self.sign_in_problem = problems.noted(self.request)
            raise
