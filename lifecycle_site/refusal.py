"""One shape for a request the site does not carry out, whatever refuses it (the operations, the
gateway link, the alerts): ``code`` for programs, ``message`` for people, ``status`` the HTTP
status, ``details`` more fields of the API's error object. Every adapter renders it the same way:
the API as ``{"error": {"code", "message", ...details}}`` (api/auth.py ``api_view``), the pages as
the message where the answer goes, the CLI as the message on stderr (and that JSON with --json)."""
from __future__ import annotations

from typing import Any


class Refusal(Exception):
    status = 400

    def __init__(self, code: str, message: str, status: int | None = None, **details: Any) -> None:
        super().__init__(message)
        self.code, self.message, self.details = code, message, details
        if status is not None:
            self.status = status

    def as_json(self) -> dict:
        return {"error": {"code": self.code, "message": self.message, **self.details}}
