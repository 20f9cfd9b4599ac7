"""After LocaleMiddleware (cookie, Accept-Language) and the authentication: a signed-in user's own
choice wins, from their session (remember_at_login puts it there)."""
from __future__ import annotations

from django.http import HttpRequest
from django.utils import translation

from lifecycle_site.languages.choice import SESSION_KEY, supported


class UserLanguageMiddleware:
    def __init__(self, get_response) -> None:
        self.get_response = get_response

    def __call__(self, request: HttpRequest):
        chosen = supported(request.session.get(SESSION_KEY)) if hasattr(request, "session") else None
        if chosen and chosen != getattr(request, "LANGUAGE_CODE", None):
            translation.activate(chosen)
            request.LANGUAGE_CODE = chosen
        return self.get_response(request)
