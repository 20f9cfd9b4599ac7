"""Which language a page or a live socket is shown in: the user's choice (kept in their session
from the login on), else the language cookie (set by the same choice, so the login page after a
logout keeps it), else the browser's Accept-Language, else settings.LANGUAGE_CODE
(LIFECYCLE_LANGUAGE)."""
from __future__ import annotations

from http.cookies import CookieError, SimpleCookie
from typing import Any

from django.conf import settings
from django.http import HttpRequest
from django.utils import translation
from django.utils.translation import trans_real

SESSION_KEY = "language"


def supported(code: str | None) -> str | None:
    """``code`` as one of settings.LANGUAGES ("de-AT" -> "de"), or None."""
    if not code:
        return None
    try:
        return translation.get_supported_language_variant(code)
    except LookupError:
        return None


def remember_at_login(sender, request: HttpRequest, user, **_: Any) -> None:
    """user_logged_in: the user's choice into the new session (no query per request after it)."""
    from lifecycle_site.languages.models import LanguageChoice

    chosen = LanguageChoice.objects.filter(user=user).values_list("language", flat=True).first()
    if chosen and supported(chosen):
        request.session[SESSION_KEY] = chosen


def of_scope(scope: dict) -> str:
    """The language of a WebSocket connection, by the same rules as its page. Reads the session
    (a database query the first time): call it off the event loop."""
    session = scope.get("session")
    chosen = supported(session.get(SESSION_KEY)) if session is not None else None
    if chosen:
        return chosen
    headers = dict(scope.get("headers", []))
    cookies: SimpleCookie | dict = SimpleCookie()
    try:
        cookies.load(headers.get(b"cookie", b"").decode("latin-1"))
    except CookieError:  # a malformed cookie header: as if there were none
        cookies = {}
    cookie = cookies.get(settings.LANGUAGE_COOKIE_NAME)
    chosen = supported(cookie.value if cookie is not None else None)
    if chosen:
        return chosen
    for code, _quality in trans_real.parse_accept_lang_header(headers.get(b"accept-language", b"").decode("latin-1")):
        chosen = supported(code) if code != "*" else None
        if chosen:
            return chosen
    return supported(settings.LANGUAGE_CODE) or "en"
