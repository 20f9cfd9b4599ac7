"""Signing in with the company's OpenID Connect provider: a real provider process (authorization
code flow, PKCE required, nonce required, RS256 keys), the real site views and backend. The
browser's part (following redirects, choosing the user on the provider's page) is played with
requests and Django's test client; tests/browser/test_company_sign_in.py plays it in Chromium."""
from __future__ import annotations

import json
import socket
import threading
import time
from contextlib import contextmanager
from functools import partial
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import parse_qs, urlsplit

import pytest
import requests
from django.contrib.auth import get_user_model
from django.test import Client, override_settings
from django.utils.html import escape

from lifecycle_site.audit.models import AccessDenial
from lifecycle_site.sign_in import config, discovery, problems
from lifecycle_site.sign_in.models import DirectoryAccount
from tests.conftest import make_user
from tests.sign_in.oidc_provider import Provider, start_provider

CALLBACK = "http://testserver/oidc/callback/"
ROLES = "viewer=plant-staff;operator=lifecycle-operators;admin=plant-it"
TIMEOUT_S = 3
USERS = [
    {"sub": "u-1001", "email": "olga@plant.example", "preferred_username": "olga", "given_name": "Olga",
     "groups": ["lifecycle-operators"]},
    {"sub": "u-1002", "email": "vic@plant.example", "preferred_username": "vic", "groups": ["visitors"]},
    {"sub": "u-1003", "email": "lena@plant.example", "preferred_username": "lena", "groups": ["plant-staff"]},
]


@pytest.fixture(scope="module")
def provider(tmp_path_factory) -> Provider:
    provider = start_provider(tmp_path_factory.mktemp("oidc"), USERS)
    try:
        yield provider
    finally:
        provider.stop()


@pytest.fixture(scope="module")
def site_settings(provider):
    endpoints = provider.endpoints()
    client_id, secret = provider.register_client(CALLBACK)
    oidc = config.oidc_settings({
        "LIFECYCLE_OIDC_CLIENT_ID": client_id, "LIFECYCLE_OIDC_CLIENT_SECRET": secret,
        "LIFECYCLE_OIDC_AUTHORIZATION_URL": endpoints["authorization_endpoint"],
        "LIFECYCLE_OIDC_TOKEN_URL": endpoints["token_endpoint"],
        "LIFECYCLE_OIDC_USERINFO_URL": endpoints["userinfo_endpoint"],
        "LIFECYCLE_OIDC_JWKS_URL": endpoints["jwks_uri"],
        "LIFECYCLE_OIDC_LOGOUT_URL": endpoints["end_session_endpoint"],
        "LIFECYCLE_OIDC_ROLES": ROLES, "LIFECYCLE_OIDC_TIMEOUT": str(TIMEOUT_S), "LIFECYCLE_OIDC_NAME": "Plant ID"})
    with override_settings(**oidc, OIDC_ON=True, AUTHENTICATION_BACKENDS=[
            "axes.backends.AxesStandaloneBackend", "django.contrib.auth.backends.ModelBackend",
            "lifecycle_site.sign_in.oidc.Backend"]):
        yield oidc


def to_provider(client: Client) -> str:
    """The site's redirect to the provider's authorization endpoint (checked for PKCE and nonce)."""
    answer = client.get("/oidc/authenticate/")
    assert answer.status_code == 302, answer
    query = parse_qs(urlsplit(answer["Location"]).query)
    assert query["code_challenge_method"] == ["S256"] and len(query["code_challenge"][0]) == 43
    assert query["nonce"] and query["state"] and query["response_type"] == ["code"]
    return answer["Location"]


def choose(authorization_url: str, sub: str, **form: str) -> str:
    """The user picks ``sub`` on the provider's page: the site's callback address it sends back."""
    answer = requests.post(authorization_url, data={"sub": sub, **form}, allow_redirects=False, timeout=TIMEOUT_S)
    assert answer.status_code == 302, answer.text
    assert answer.headers["Location"].startswith(CALLBACK), answer.headers["Location"]
    return answer.headers["Location"]


def back_to_site(client: Client, callback_url: str):
    parts = urlsplit(callback_url)
    return client.get(f"{parts.path}?{parts.query}")


def sign_in(client: Client, sub: str):
    return back_to_site(client, choose(to_provider(client), sub))


def login_page_says(client: Client, answer, problem: problems.Problem) -> None:
    assert answer.status_code == 302 and answer["Location"] == "/login/", answer
    page = client.get("/login/")
    words = escape(str(problem.words))  # (as the page writes them: "site's" is "site&#x27;s")
    assert f'data-problem="{problem.code}"' in page.text and words in page.text, page.text
    assert words not in client.get("/login/").text  # said once, not on every later visit


@pytest.mark.django_db
def test_the_login_page_offers_the_provider(site_settings):
    page = Client().get("/login/")
    assert "Sign in with Plant ID" in page.text and 'href="/oidc/authenticate/"' in page.text


@pytest.mark.django_db
def test_a_first_sign_in_makes_the_account_with_the_role_of_its_groups(site_settings, provider):
    client = Client()
    answer = sign_in(client, "u-1001")
    assert answer.status_code == 302 and answer["Location"] == "/", answer
    assert client.get("/").status_code == 200
    # It ends 12 hours after the sign-in (LIFECYCLE_DIRECTORY_SESSION_HOURS), when the groups are read again.
    assert 12 * 3600 - 60 < client.session.get_expiry_age() <= 12 * 3600
    user = get_user_model().objects.get(directory_account__subject="u-1001")
    assert (user.username, user.email, user.first_name) == ("olga", "olga@plant.example", "Olga")
    assert not user.has_usable_password()
    assert list(user.groups.values_list("name", flat=True)) == ["operator"]
    assert user.directory_account.source == DirectoryAccount.OIDC

    # The provider moves her to plant-it: admin at the next sign-in, found by subject, not by name.
    changed = dict(USERS[0], groups=["plant-it"], preferred_username="olga.k")
    requests.put(f"{provider.issuer}/users/u-1001", json={k: v for k, v in changed.items() if k != "sub"},
                 timeout=TIMEOUT_S).raise_for_status()
    try:
        assert sign_in(Client(), "u-1001").status_code == 302
    finally:
        requests.put(f"{provider.issuer}/users/u-1001", json={k: v for k, v in USERS[0].items() if k != "sub"},
                     timeout=TIMEOUT_S).raise_for_status()
    user.refresh_from_db()
    assert user.username == "olga" and list(user.groups.values_list("name", flat=True)) == ["admin"] and user.is_staff


@pytest.mark.django_db
def test_no_mapped_group_is_refused_in_words_and_on_record(site_settings):
    client = Client()
    login_page_says(client, sign_in(client, "u-1002"), problems.NO_ROLE)
    assert not DirectoryAccount.objects.filter(subject="u-1002").exists()
    assert not get_user_model().objects.filter(username="vic").exists()
    denial = AccessDenial.objects.order_by("-id").first()
    assert (denial.code, denial.detail) == ("login_failed", problems.NO_ROLE.summary)


@pytest.mark.django_db
def test_a_local_accounts_name_is_not_taken(site_settings):
    local = make_user("lena", "admin")
    client = Client()
    assert sign_in(client, "u-1003").status_code == 302
    user = get_user_model().objects.get(directory_account__subject="u-1003")
    assert user.pk != local.pk and user.username.startswith("lena-")
    assert list(user.groups.values_list("name", flat=True)) == ["viewer"]
    assert list(local.groups.values_list("name", flat=True)) == ["admin"]  # untouched


@pytest.mark.django_db
def test_a_provider_down_at_the_token_exchange_is_a_bounded_refusal(site_settings, provider):
    client = Client()
    callback = choose(to_provider(client), "u-1001")
    provider.stop()
    try:
        started = time.monotonic()
        answer = back_to_site(client, callback)
        assert time.monotonic() - started < TIMEOUT_S + 2
    finally:
        provider.start()
    login_page_says(client, answer, problems.PROVIDER_UNREACHABLE)
    assert AccessDenial.objects.order_by("-id").first().detail == problems.PROVIDER_UNREACHABLE.summary
    assert sign_in(Client(), "u-1001").status_code == 302  # and back


@pytest.mark.django_db
def test_a_declined_replayed_or_foreign_sign_in_ends_on_the_login_page(site_settings):
    client = Client()
    login_page_says(client, back_to_site(client, choose(to_provider(client), "u-1001", action="deny")),
                    problems.PROVIDER_REFUSED)

    callback = choose(to_provider(client), "u-1001")
    assert back_to_site(client, callback).status_code == 302 and client.get("/").status_code == 200
    client.post("/logout/")
    login_page_says(client, back_to_site(client, callback), problems.SIGN_IN_EXPIRED)  # the same answer again

    stranger = Client()  # a callback this browser never started (sent by someone else)
    login_page_says(stranger, back_to_site(stranger, choose(to_provider(Client()), "u-1001")),
                    problems.SIGN_IN_EXPIRED)
    assert AccessDenial.objects.filter(detail=problems.SIGN_IN_EXPIRED.summary).count() == 2


@pytest.mark.django_db
def test_logging_out_ends_the_providers_session_too(site_settings, provider):
    client = Client()
    assert sign_in(client, "u-1001").status_code == 302
    answer = client.post("/logout/")
    assert answer.status_code == 302
    location = urlsplit(answer["Location"])
    assert f"{location.scheme}://{location.netloc}{location.path}" == provider.endpoints()["end_session_endpoint"]
    query = parse_qs(location.query)
    assert query["post_logout_redirect_uri"] == ["http://testserver/login/"]
    assert query["id_token_hint"][0].count(".") == 2  # the ID token: header.payload.signature
    assert client.get("/")["Location"].startswith("/login/")  # the site's session is over


@pytest.mark.django_db
def test_axes_blocks_the_provider_path_too(site_settings, settings):
    for attempt in range(settings.AXES_FAILURE_LIMIT):  # from this address, several names
        Client().post("/login/", {"username": f"guess-{attempt}", "password": "wrong"})
    answer = sign_in(Client(), "u-1001")  # the provider vouches for her, but this address is blocked
    assert answer.status_code == 429 and "Login blocked for now" in answer.text
    assert not DirectoryAccount.objects.filter(subject="u-1001").exists()
    assert AccessDenial.objects.order_by("-id").first().code == "login_blocked"


@contextmanager
def serving_documents():
    """A web server on 127.0.0.1 whose discovery URL answers the next of ``documents`` (a dict as
    JSON, bytes as they are, None: 404, a function: it answers, given the handler); yields (its
    issuer URL, documents)."""
    documents: list = []

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802 (http.server's name)
            document = documents.pop(0) if documents else None
            if callable(document):
                document(self)
                return
            if document is None or self.path != discovery.WELL_KNOWN:
                self.send_error(404)
                return
            body = document if isinstance(document, bytes) else json.dumps(document).encode()
            self.send_response(200)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args):
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}", documents
    finally:
        server.shutdown()
        server.server_close()
        thread.join(5)


def answer_slowly(handler, length: int, pause: float) -> None:
    """Headers for a body of ``length`` bytes, then fewer, a byte every ``pause`` s (0: at once)."""
    handler.send_response(200)
    handler.send_header("Content-Length", str(length))
    handler.end_headers()
    try:
        for _ in range(length // 4):
            handler.wfile.write(b" ")
            handler.wfile.flush()
            time.sleep(pause)
    except (BrokenPipeError, ConnectionResetError):  # the site stopped reading
        pass


@pytest.fixture
def by_issuer(provider, site_settings):
    """The same client, configured by the provider's issuer alone (its discovery document names the
    endpoints); ``use(issuer)`` switches to another issuer."""
    def use(issuer: str) -> None:
        oidc = config.oidc_settings({
            "LIFECYCLE_OIDC_CLIENT_ID": site_settings["OIDC_RP_CLIENT_ID"],
            "LIFECYCLE_OIDC_CLIENT_SECRET": site_settings["OIDC_RP_CLIENT_SECRET"],
            "LIFECYCLE_OIDC_ISSUER": issuer, "LIFECYCLE_OIDC_ROLES": ROLES, "LIFECYCLE_OIDC_TIMEOUT": str(TIMEOUT_S)})
        overridden = override_settings(**oidc)
        overridden.enable()
        undo.append(overridden)
        discovery.forget()

    undo: list = []
    try:
        yield use
    finally:
        for overridden in reversed(undo):
            overridden.disable()
        discovery.forget()


@pytest.mark.django_db
def test_with_the_issuer_alone_the_endpoints_come_from_its_discovery_document(by_issuer, provider):
    by_issuer(provider.issuer + "/")  # (as often copied, with a trailing slash)
    client = Client()
    answer = sign_in(client, "u-1001")
    assert answer.status_code == 302 and answer["Location"] == "/", answer
    user = get_user_model().objects.get(directory_account__subject="u-1001")
    assert list(user.groups.values_list("name", flat=True)) == ["operator"]
    location = urlsplit(client.post("/logout/")["Location"])  # the discovered end-session endpoint
    assert f"{location.scheme}://{location.netloc}{location.path}" == provider.endpoints()["end_session_endpoint"]


@pytest.mark.django_db
def test_a_wrong_or_unreachable_issuer_is_a_refusal_in_words_and_on_record(by_issuer, provider):
    client = Client()
    with serving_documents() as (issuer, documents):
        # A document naming another issuer than the one asked (a stranger's), one whose endpoint is
        # not an http URL, one that is not JSON, none at all (404): none is used, each refused.
        documents.extend([{**provider.endpoints(), "issuer": "https://idp.elsewhere"},
                          {**provider.endpoints(), "issuer": issuer, "authorization_endpoint": "javascript:x"},
                          {**provider.endpoints(), "issuer": issuer, "token_endpoint": "https://[::1/token"},
                          b"<html>not here</html>", None])
        by_issuer(issuer)
        for _ in range(5):
            discovery.forget()
            login_page_says(client, client.get("/oidc/authenticate/"), problems.PROVIDER_ANSWER_INVALID)
        assert AccessDenial.objects.filter(detail=problems.PROVIDER_ANSWER_INVALID.summary).count() == 5

        # A body cut short, and one dripped a byte at a time: not reached, within the time-out in all.
        documents.extend([partial(answer_slowly, length=500, pause=0), partial(answer_slowly, length=400, pause=0.2)])
        for _ in range(2):
            discovery.forget()
            started = time.monotonic()
            answer = client.get("/oidc/authenticate/")
            assert time.monotonic() - started < TIMEOUT_S + 1.5
            login_page_says(client, answer, problems.PROVIDER_UNREACHABLE)

        # The provider's issuer ends in a slash (Auth0's do), the setting does not keep it: the same.
        documents.append({**provider.endpoints(), "issuer": issuer + "/"})
        discovery.forget()
        assert client.get("/oidc/authenticate/")["Location"].startswith(provider.endpoints()["authorization_endpoint"])

    with socket.socket() as closed:  # a port nobody listens on
        closed.bind(("127.0.0.1", 0))
        port = closed.getsockname()[1]
    by_issuer(f"http://127.0.0.1:{port}")
    started = time.monotonic()
    answer = client.get("/oidc/authenticate/")
    assert time.monotonic() - started < TIMEOUT_S + 2
    login_page_says(client, answer, problems.PROVIDER_UNREACHABLE)
    assert AccessDenial.objects.order_by("-id").first().detail == problems.PROVIDER_UNREACHABLE.summary
    assert client.post("/logout/").status_code == 302  # nothing to end at the provider: the site's session only

    by_issuer(provider.issuer)  # the right one again: read afresh
    assert sign_in(Client(), "u-1001")["Location"] == "/"
