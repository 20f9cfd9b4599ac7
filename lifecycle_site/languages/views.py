"""POST /language/: the language chosen in the page header, for this user everywhere (and in a
cookie for the login page), then back to the page it was chosen on."""
from __future__ import annotations

from django.conf import settings
from django.http import HttpRequest, HttpResponse, HttpResponseBadRequest, HttpResponseRedirect
from django.utils.http import url_has_allowed_host_and_scheme
from django.views.decorators.http import require_POST

from lifecycle_site.languages.choice import SESSION_KEY, supported
from lifecycle_site.languages.models import LanguageChoice


@require_POST
def choose(request: HttpRequest) -> HttpResponse:
    language = supported(request.POST.get("language"))
    if language is None or language not in dict(settings.LANGUAGES):
        return HttpResponseBadRequest("Unknown language.")
    back = request.POST.get("next", "")
    if not url_has_allowed_host_and_scheme(back, allowed_hosts={request.get_host()},
                                           require_https=request.is_secure()):
        back = settings.URL_PREFIX + "/"
    if request.user.is_authenticated:
        LanguageChoice.objects.update_or_create(user=request.user, defaults={"language": language})
        request.session[SESSION_KEY] = language
    response = HttpResponseRedirect(back)
    response.set_cookie(settings.LANGUAGE_COOKIE_NAME, language, max_age=365 * 24 * 3600, samesite="Lax",
                        secure=settings.SESSION_COOKIE_SECURE, httponly=True)
    return response
