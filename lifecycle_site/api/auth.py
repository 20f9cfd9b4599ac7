"""How API requests are authenticated: a bearer token, or the browser's session (with CSRF)."""
from __future__ import annotations

import json
import logging
import math
from datetime import datetime
from functools import wraps
from typing import Any, Callable

from django.conf import settings
from django.core.exceptions import RequestDataTooBig, SuspiciousOperation, TooManyFieldsSent
from django.db import DataError, InterfaceError, OperationalError
from django.http import Http404, HttpRequest, JsonResponse
from django.middleware.csrf import CsrfViewMiddleware
from django.utils import timezone
from django.utils.translation import gettext as _
from django.utils.translation import gettext_lazy, pgettext
from django.views.decorators.csrf import csrf_exempt

from lifecycle_site.api import grants
from lifecycle_site.api.limits import MAX_DEPTH, MAX_DIGITS, body_limit, size_text
from lifecycle_site.api.models import ApiToken, hash_token
from lifecycle_site.audit import denials
from lifecycle_site.database_input import MESSAGE as DATA_ERROR_MESSAGE
from lifecycle_site.refusal import Refusal, cut, in_english
from lifecycle_site.sign_in import directory_check
from ros_gateway.shared import param_types as pt

UNSAFE_METHODS = {"POST", "PUT", "PATCH", "DELETE"}
log = logging.getLogger(__name__)
DATABASE_DOWN_MESSAGE = gettext_lazy(
    "The site's database did not answer; try again in a moment. If you asked for a change, look "
    "at the node before asking again: a change that reached the robot is recorded from its "
    "gateway's report once the database answers."
)


def error(code: str, message: str, status: int, **details) -> JsonResponse:
    """The one error shape of the API: {"error": {"code", "message", ...details}}; ``message`` in
    the request's language (a lazy translation is made text here)."""
    return refusal_response(Refusal(code, message, status, **details))


class NonFiniteNumber(ValueError):
    """JSON text holds NaN, Infinity, -Infinity or a number too large for a double (1e999).

    Python's json module accepts these (1e999 becomes inf), but they are not JSON, no ROS
    double can use them, and an audit record cannot store them."""

    def __init__(self, literal: str, path: tuple) -> None:
        self.literal = literal
        self.path = path
        values = {"literal": literal, "path": pt.path_text(path) if path else ""}
        if path:
            text = _("%(literal)s at %(path)s is not a finite number (NaN, Infinity, -Infinity and numbers beyond "
                     "±1.8e308, such as 1e999, cannot be used)") % values
        else:
            text = _("%(literal)s is not a finite number (NaN, Infinity, -Infinity and numbers beyond ±1.8e308, "
                     "such as 1e999, cannot be used)") % values
        super().__init__(text)


class TooDeep(ValueError):
    """Lists or objects nested deeper than MAX_DEPTH."""


class TooManyDigits(ValueError):
    """An integer longer than MAX_DIGITS digits."""

    def __init__(self, digits: int) -> None:
        super().__init__(_("a number has %(digits)s digits; at most %(most)s are accepted") % {
            "digits": f"{digits:,}", "most": f"{MAX_DIGITS:,}"})


class _Literal(str):
    """How a non-finite number's own text is kept while parsing, to name it in the refusal."""


def _float(text: str) -> float | _Literal:
    value = float(text)
    return value if math.isfinite(value) else _Literal(text)


def _int(text: str) -> int:
    digits = len(text) - text.startswith("-")
    if digits > MAX_DIGITS:  # int() would refuse it too, with advice meant for programmers
        raise TooManyDigits(digits)
    return int(text)


def _first_literal(value: Any, path: tuple = ()) -> tuple[tuple, str] | None:
    """The first non-finite number's place and text; TooDeep past MAX_DEPTH levels."""
    if isinstance(value, _Literal):
        return path, str(value)
    items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    if items and len(path) >= MAX_DEPTH:
        raise TooDeep
    for key, item in items:
        found = _first_literal(item, (*path, key))
        if found is not None:
            return found
    return None


def loads_finite(text: str | bytes) -> Any:
    """``json.loads``, but NaN, Infinity, -Infinity and numbers too large for a double, anywhere
    in the document (nested lists included), raise NonFiniteNumber naming the first one.
    TooDeep for lists or objects nested deeper than MAX_DEPTH, TooManyDigits for an integer
    longer than MAX_DIGITS."""
    try:
        document = json.loads(text, parse_constant=_Literal, parse_float=_float, parse_int=_int)
    except RecursionError:  # the parser nests a call per level: thousands of "[" end here
        raise TooDeep from None
    found = _first_literal(document)
    if found is not None:
        path, literal = found
        raise NonFiniteNumber(literal, path)
    return document


def json_body(request: HttpRequest, empty: bytes = b"", *, shape: type | None = None, wanted: str = ""):
    """The request body parsed as JSON; a Refusal (400: malformed_json, or non_finite_number for
    NaN, Infinity, -Infinity, 1e999; 413 too large) when it cannot be, nothing sent to a robot.

    ``empty`` stands in for an empty body (b"" keeps an empty body malformed); with ``shape``
    (dict, list) anything else is refused as malformed_json, ``wanted`` saying what to send."""
    try:
        body = loads_finite(request.body or empty)
    except RequestDataTooBig:
        raise too_large() from None
    except TooDeep:
        text = _("Nothing was sent: the request body nests lists or objects deeper than %(depth)s levels; no "
                 "endpoint takes more than 3.") % {"depth": MAX_DEPTH}
        raise Refusal("too_deep", text) from None
    except TooManyDigits as exc:
        raise Refusal("malformed_json", _("Nothing was sent: %(reason)s.") % {"reason": exc}) from None
    except NonFiniteNumber as exc:
        raise Refusal("non_finite_number", _("Nothing was sent: %(reason)s.") % {"reason": exc}, value=exc.literal,
                      path=list(exc.path)) from None
    except UnicodeDecodeError as exc:
        raise Refusal("malformed_json", _("The request body is not UTF-8 text: %(error)s.") % {"error": exc}) from None
    except ValueError as exc:
        raise Refusal("malformed_json", _("The request body is not valid JSON: %(error)s.") % {"error": exc}) from None
    if shape is not None and not isinstance(body, shape):
        raise Refusal("malformed_json", _shape_refusal(shape, wanted))
    return body


def _shape_refusal(shape: type, wanted: str) -> str:
    """"The request body must be a JSON object" (or list), and what to send (``wanted``)."""
    if shape is dict:
        if wanted:
            return _("The request body must be a JSON object %(wanted)s.") % {"wanted": wanted}
        return _("The request body must be a JSON object.")
    if wanted:
        return _("The request body must be a JSON list %(wanted)s.") % {"wanted": wanted}
    return _("The request body must be a JSON list.")


def too_large() -> Refusal:
    limit = size_text(body_limit())
    return Refusal("body_too_large", _("The request body is larger than %(limit)s, the most this site takes; "
                                       "nothing was done.") % {"limit": limit}, 413, limit=body_limit())


def body_too_large() -> JsonResponse:
    return refusal_response(too_large())


def refusal_response(refusal: Refusal) -> JsonResponse:
    """Every refusal in the API's one error shape."""
    return JsonResponse(refusal.as_json(), status=refusal.status)


class TokenRefused(Refusal):
    """A real token refused for what became of its account: said why, on record, and not counted
    as a guessed token toward the address's block. ``english``: the record's summary."""

    status = 401


def _switched_off(username: str) -> TokenRefused:
    """A token of an account an admin switched off (Admin → Users, "active")."""
    return TokenRefused("account_off", _("This token belongs to %(user)s, whose account is switched off. Ask an "
                                         "administrator.") % {"user": username},
                        english=f"token of switched-off account {username}")


def _dormant(username: str, days: float) -> TokenRefused:
    """A directory account's token, used longer than LIFECYCLE_DIRECTORY_TOKEN_DAYS after the
    account last signed in (its role may be gone in the directory since)."""
    values = {"user": username, "days": f"{days:g}"}
    return TokenRefused("token_dormant", _(
        "This token belongs to %(user)s, a company account that has not signed in here for %(days)s days (its role "
        "comes from the company directory at sign-in). Its tokens work again once it signs in on the site.") % values,
        english="token of directory account %(user)s, which has not signed in for %(days)s days" % values)


def _disowned(username: str, why: str = "is no longer vouched for by the directory") -> TokenRefused:
    """A directory account's token, whose account the directory no longer vouches for: it said it
    has no such account or has it switched off (sign_in.directory_check), until a sign-in."""
    return TokenRefused("directory_refused", _(
        "This token belongs to %(user)s, a company account that the company directory no longer has or has switched "
        "off. Its tokens work again once it signs in on the site (which the directory must allow).") % {
        "user": username}, english=f"token of directory account {username}, which {why}; refused until it signs in "
                                   "again")


def _token_user(request: HttpRequest):
    """The token's user; None for no or an unknown token; TokenRefused for one of a switched-off
    account, of a directory account not signed in for LIFECYCLE_DIRECTORY_TOKEN_DAYS, or of one
    the directory no longer has (asked now and then: sign_in.directory_check)."""
    header = request.headers.get("Authorization", "")
    scheme, _, token = header.partition(" ")
    if scheme.lower() != "bearer" or not token.strip():
        return None
    digest = hash_token(token.strip())
    grant = grants.cached(digest) or grants.load(digest)
    if grant is None:
        return None
    if not grant.is_active:
        raise _switched_off(grant.user().get_username())
    if directory_check.due(grant.user_id, grant.directory, grant.vouched):
        owner = grant.user_id
        try:
            directory_check.check(owner)
        except directory_check.Gone as gone:
            raise _disowned(gone.username, gone.why) from None
        finally:  # the account as the directory left it, for every token of it (not all changes signal)
            grants.forget(lambda _digest, kept: kept.user_id == owner)
        grant = grants.load(digest)  # with the role the directory gives now
        if grant is None:
            return None
        if not grant.is_active:
            raise _switched_off(grant.user().get_username())
    now = timezone.now()
    days = settings.LIFECYCLE_DIRECTORY_TOKEN_DAYS
    if grant.directory and grant.vouched is None:  # disowned by the directory (directory_check)
        raise _disowned(grant.user().get_username())
    if grant.directory and (now - grant.vouched).total_seconds() > days * 86400:
        raise _dormant(grant.user().get_username(), days)
    # Cheap enough once a minute, and tells an admin which tokens are still in use.
    if grant.last_used is None or (now - grant.last_used).total_seconds() > grants.LAST_USED_EVERY_S:
        grant.last_used = now
        ApiToken.objects.filter(pk=grant.token_id).update(last_used=now)
    return grant.user()


def _csrf_failure(request: HttpRequest) -> JsonResponse | None:
    check = CsrfViewMiddleware(lambda req: None)
    check.process_request(request)
    rejection = check.process_view(request, None, (), {})
    if rejection is not None:
        return error("csrf_failed", _("CSRF check failed: send the X-CSRFToken header with session auth."), 403)
    return None


def _token_blocked(request: HttpRequest, until: datetime) -> JsonResponse:
    """429 for a token request from an address blocked for guessing tokens, with when it ends."""
    wait = max(1, math.ceil((until - timezone.now()).total_seconds()))
    when = until.isoformat(timespec="seconds")
    denials.record(request, 429, "token_blocked", f"too many invalid tokens from this address; blocked until {when}")
    response = error(
        "too_many_attempts", _("Too many invalid tokens from this address: every token request from it is refused, "
                               "unchecked, until %(when)s (in %(wait)s s).") % {"when": when, "wait": wait},
        429, retry_after=wait, until=until.isoformat(),
    )
    response["Retry-After"] = str(wait)
    return response


VIEW_PERMISSION = "fleet.view_managednode"


def api_view(methods: tuple[str, ...] = ("GET",), permission: str = VIEW_PERMISSION) -> Callable:
    """Authenticate, check method and permission (viewing by default), and turn gateway
    errors into JSON."""

    def decorate(view: Callable) -> Callable:
        @csrf_exempt
        @wraps(view)
        def wrapper(request: HttpRequest, *args, **kwargs):
            # SQLite locked past its timeout, PostgreSQL down or gone: whether in the token
            # check or in the view, the API's own error shape, not Django's HTML 500.
            try:
                return checked(request, *args, **kwargs)
            except (OperationalError, InterfaceError) as exc:
                log.error("API %s %s: the database did not answer: %s", request.method,
                          in_english(cut, request.path), exc)
                return error("database_unavailable", DATABASE_DOWN_MESSAGE, 503)

        def checked(request: HttpRequest, *args, **kwargs):
            if request.method not in methods:
                either = " " + pgettext("between HTTP methods", "or") + " "
                return error("method_not_allowed", _("Use %(methods)s here.") % {"methods": either.join(methods)}, 405)
            if "Authorization" in request.headers:
                # The block is the address's: every token it sends is refused unchecked, a valid
                # one too (one query per token request), and each refusal is on record.
                until = denials.token_block_until(request)
                if until is not None:
                    return _token_blocked(request, until)
            try:
                user = _token_user(request)
            except TokenRefused as refused:  # (on record under its own code: not a guessed token)
                denials.record(request, refused.status, refused.code, refused.english)
                return refusal_response(refused)
            if user is None and "Authorization" in request.headers:
                denials.record(request, 401, "bad_token", "the bearer token is not valid (or revoked)")
                return error("unauthorized", _("The bearer token is not valid."), 401)
            if user is None:
                if not request.user.is_authenticated:
                    if request.method in UNSAFE_METHODS:
                        denials.record(request, 401, "unauthorized", "neither a session nor a token")
                    return error("unauthorized", _("Log in or send 'Authorization: Bearer TOKEN'."), 401)
                if request.method in UNSAFE_METHODS:
                    failure = _csrf_failure(request)
                    if failure is not None:  # on record already (CSRF_FAILURE_VIEW)
                        return failure
                user = request.user
            request.user = user
            request.api_source = "api"
            if not user.has_perm(permission):
                needed = "viewer" if permission == VIEW_PERMISSION else "operator or admin"
                if request.method in UNSAFE_METHODS or permission != VIEW_PERMISSION:
                    denials.record(request, 403, "forbidden", f"{needed} needed")  # (on record: in English)
                return error("forbidden", lacks_role(needed), 403)
            try:
                return view(request, *args, **kwargs)
            except Http404 as exc:
                return error("not_found", str(exc) or _("Not found."), 404)
            except Refusal as refusal:  # the operations', the gateway link's, the alerts'
                return refusal_response(refusal)
            except RequestDataTooBig:
                return body_too_large()
            except TooManyFieldsSent:
                return error("too_many_fields", _("The query string has more than %(most)s fields; send fewer.") % {
                    "most": f"{settings.DATA_UPLOAD_MAX_NUMBER_FIELDS:,}"}, 400)
            except SuspiciousOperation as exc:  # Django's other refusals of a malformed request
                return error("bad_request", _("The request was refused: %(reason)s") % {"reason": exc}, 400)
            except DataError:  # PostgreSQL: a NUL character, or text longer than its column
                return error("bad_request", DATA_ERROR_MESSAGE, 400)

        return wrapper

    return decorate


def lacks_role(needed: str) -> str:
    """The refusal of a request the account's role does not allow; ``needed``: "viewer",
    "operator or admin" or "admin" (as the record of the denial names it)."""
    roles = {"viewer": _("viewer"), "operator or admin": _("operator or admin"), "admin": _("admin")}
    return _("Your account lacks the role for this (%(needed)s needed).") % {"needed": roles.get(needed, needed)}


@csrf_exempt  # a POST to an unknown path is a 404, not a CSRF refusal
def not_found(request: HttpRequest, path: str = "") -> JsonResponse:
    """Unknown API paths answer in JSON too, whatever the method."""
    where = "/api/v1/" + path
    return error("not_found", _("There is no API endpoint %(path)s; see docs/api.md.") % {"path": cut(where)}, 404)


def bad_request(request: HttpRequest, exception: Exception | None = None):
    """For handler400 in lifecycle_site/urls.py: what Django refuses before any view (a Host not
    in ALLOWED_HOSTS, too many fields) in the error shape under /api/, its own page elsewhere."""
    if not request.path_info.startswith("/api/"):
        from django.views.defaults import bad_request as page

        return page(request, exception)
    if isinstance(exception, RequestDataTooBig):
        return body_too_large()
    reason = cut(str(exception)) if exception else _("malformed request")
    return error("bad_request", _("The request was refused: %(reason)s") % {"reason": reason}, 400)
