"""Company sign-in in Chromium against a site process configured as a plant would (environment
variables): OpenID Connect through the provider's own pages (PKCE, and a logout that ends the
provider's session under the Content-Security-Policy), and the company directory (a real slapd
over StartTLS) through the login form, in German for a German browser."""
from __future__ import annotations

import sys

import pytest
from playwright.sync_api import expect

from lifecycle_site.sign_in import problems
from tests import stack
from tests.browser.conftest import submit_login
from tests.sign_in.oidc_provider import start_provider
from tests.sign_in.slapd import start_directory

WAIT_MS = 20_000
PASSWORD = "a directory password 1"
ROLES = "viewer=plant-staff;operator=lifecycle-operators;admin=plant-it"
USERS = [{"sub": "u-2001", "email": "paula@plant.example", "preferred_username": "paula",
          "groups": ["lifecycle-operators"]}]


@pytest.fixture(scope="module")
def servers(tmp_path_factory):
    directory = start_directory(tmp_path_factory.mktemp("slapd"))
    provider = start_provider(tmp_path_factory.mktemp("oidc"), USERS)
    try:
        directory.add_user("dieter", PASSWORD, groups=["lifecycle-operators"], given_name="Dieter")
        directory.add_user("gast", PASSWORD, groups=["visitors"])
        yield directory, provider
    finally:
        provider.stop()
        directory.stop()


@pytest.fixture(scope="module")
def sign_in_site(redis_server, live_db, servers):
    directory, provider = servers
    port = stack.free_port()
    endpoints = provider.endpoints()
    client_id, secret = provider.register_client(f"http://127.0.0.1:{port}/oidc/callback/")
    env = stack.environment(
        LIFECYCLE_OIDC_CLIENT_ID=client_id, LIFECYCLE_OIDC_CLIENT_SECRET=secret,
        LIFECYCLE_OIDC_AUTHORIZATION_URL=endpoints["authorization_endpoint"],
        LIFECYCLE_OIDC_TOKEN_URL=endpoints["token_endpoint"],
        LIFECYCLE_OIDC_USERINFO_URL=endpoints["userinfo_endpoint"],
        LIFECYCLE_OIDC_JWKS_URL=endpoints["jwks_uri"], LIFECYCLE_OIDC_LOGOUT_URL=endpoints["end_session_endpoint"],
        LIFECYCLE_OIDC_ROLES=ROLES, LIFECYCLE_OIDC_NAME="Plant ID",
        LIFECYCLE_LDAP_URL=directory.url, LIFECYCLE_LDAP_CA_FILE=directory.ca_file,
        LIFECYCLE_LDAP_USER_BASE=directory.people, LIFECYCLE_LDAP_GROUP_BASE=directory.groups,
        LIFECYCLE_LDAP_ROLES=ROLES, LIFECYCLE_LDAP_TIMEOUT="3")
    process = stack.Process("daphne-sign-in", [sys.executable, "-m", "lifecycle_site.serve", "-b", "127.0.0.1",
                                               "-p", str(port), "lifecycle_site.asgi:application"],
                            env, stack.log_dir())
    stack.wait_for(lambda: stack.listens(port) or not process.alive(), 30, "daphne to listen")
    assert process.alive(), process.output()
    yield f"http://127.0.0.1:{port}/", provider
    process.stop()


def test_openid_connect_sign_in_and_logout_through_the_providers_pages(browser, sign_in_site):
    site, provider = sign_in_site
    context = browser.new_context()
    page = context.new_page()
    blocked: list[str] = []
    page.on("console", lambda m: blocked.append(m.text) if "Content Security Policy" in m.text else None)
    try:
        page.goto(site + "login/")
        page.get_by_role("link", name="Sign in with Plant ID").click()
        expect(page.get_by_role("heading", name="Authorize Client")).to_be_visible(timeout=WAIT_MS)
        assert "code_challenge_method=S256" in page.url and "code_challenge=" in page.url
        page.get_by_role("button", name="u-2001").click()  # the provider's page: this user
        expect(page.locator("header .who")).to_have_text("paula", timeout=WAIT_MS)
        expect(page).to_have_url(site)

        page.get_by_role("button", name="Log out").click()  # a form post redirected to the provider
        expect(page.get_by_role("heading", name="End Session")).to_be_visible(timeout=WAIT_MS)
        assert page.url.startswith(provider.endpoints()["end_session_endpoint"])
        page.get_by_role("button", name="End session").click()
        expect(page).to_have_url(site + "login/", timeout=WAIT_MS)
        expect(page.get_by_role("heading", name="Log in")).to_be_visible()
        assert not blocked, blocked
    finally:
        context.close()


def test_the_directory_sign_in_speaks_german_to_a_german_browser(browser, sign_in_site):
    site, _provider = sign_in_site
    context = browser.new_context(locale="de-DE")
    page = context.new_page()
    try:
        page.goto(site + "login/")
        expect(page.get_by_role("heading", name="Anmelden")).to_be_visible()
        expect(page.get_by_role("link", name="Anmelden mit Plant ID")).to_be_visible()
        submit_login(page, "gast", PASSWORD)  # in the directory, but in no mapped group
        refusal = page.locator(f'[data-problem="{problems.NO_ROLE.code}"]')
        expect(refusal).to_contain_text("gehört keiner Gruppe an", timeout=WAIT_MS)
        submit_login(page, "dieter", PASSWORD)
        expect(page.locator("header .who")).to_have_text("dieter", timeout=WAIT_MS)
        expect(page.get_by_role("link", name="Flotte")).to_be_visible()
    finally:
        context.close()
