"""One shape for a request the site does not carry out, whatever refuses it (the operations, the
gateway link, the alerts): ``code`` for programs, ``message`` for people, ``status`` the HTTP
status, ``details`` more fields of the API's error object. Every adapter renders it the same way:
the API as ``{"error": {"code", "message", ...details}}`` (api/auth.py ``api_view``), the pages as
the message where the answer goes, the CLI as the message on stderr (and that JSON with --json).

``message`` is in the language of whoever asked (the request's, the CLI's); ``english`` is the same
message in English, for what is stored (an audit record, a run's summary: docs/translation.md)."""
from __future__ import annotations

from typing import Any, Callable

from django.utils import translation
from django.utils.translation import gettext as _

# A refused value is echoed in a message up to this many characters.
MAX_SHOWN = 80


class Refusal(Exception):
    status = 400

    def __init__(self, code: str, message: str, status: int | None = None, *, english: str | None = None,
                 **details: Any) -> None:
        message = str(message)  # (never a lazy translation: it goes into JSON)
        super().__init__(message)
        self.code, self.message, self.details = code, message, details
        self.english = message if english is None else str(english)
        if status is not None:
            self.status = status

    def as_json(self) -> dict:
        return {"error": {"code": self.code, "message": self.message, **self.details}}


def cut(text: str) -> str:
    """``text``, cut short when long (a message never echoes a whole oversized value)."""
    if len(text) <= MAX_SHOWN:
        return text
    return _("%(start)s… (%(length)s characters)") % {"start": text[:MAX_SHOWN], "length": f"{len(text):,}"}


def shown(value: Any) -> str:
    """A value a request sent, as a refusal may quote it."""
    return cut(repr(value))


def in_english(make: Callable[..., str], *args: Any, **kwargs: Any) -> str:
    """``make(*args, **kwargs)`` with English active: a message as it is stored (audit records and
    run summaries are kept in English), whatever language the person who asked reads."""
    with translation.override("en"):
        return str(make(*args, **kwargs))


def both(text: str, /, **values: Any) -> tuple[str, str]:
    """A message marked with ``gettext_noop`` (placeholders ``%(name)s``), filled in: (in the
    active language, in English), for a message that is shown and stored alike."""
    if not values:
        return _(text), text
    return _(text) % values, text % values
