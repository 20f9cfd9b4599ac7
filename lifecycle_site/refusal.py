"""One shape for a request the site does not carry out, whatever refuses it (the operations, the
gateway link, the alerts): ``code`` for programs, ``message`` for people, ``status`` the HTTP
status, ``details`` more fields of the API's error object. Every adapter renders it the same way:
the API as ``{"error": {"code", "message", ...details}}`` (api/auth.py ``api_view``), the pages as
the message where the answer goes, the CLI as the message on stderr (and that JSON with --json)."""
from __future__ import annotations

from typing import Any

# A refused value is echoed in a message up to this many characters.
MAX_SHOWN = 80


class Refusal(Exception):
    status = 400

    def __init__(self, code: str, message: str, status: int | None = None, **details: Any) -> None:
        super().__init__(message)
        self.code, self.message, self.details = code, message, details
        if status is not None:
            self.status = status

    def as_json(self) -> dict:
        return {"error": {"code": self.code, "message": self.message, **self.details}}


def cut(text: str) -> str:
    """``text``, cut short when long (a message never echoes a whole oversized value)."""
    if len(text) <= MAX_SHOWN:
        return text
    return f"{text[:MAX_SHOWN]}… ({len(text):,} characters)"


def shown(value: Any) -> str:
    """A value a request sent, as a refusal may quote it."""
    return cut(repr(value))
