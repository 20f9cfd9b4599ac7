"""The test OpenID Connect provider (tests/sign_in/oidc_provider.py) does what sign-in tests rely
on: the authorization code flow with nonce and PKCE (S256) ends in an ID token, signed with the
key its JWKS publishes, carrying sub, email and groups; PKCE is mandatory (no code_challenge, a
wrong or a missing code_verifier: refused); the end-session endpoint confirms on a form; and the
provider can be taken away and brought back knowing the same client and key."""
from __future__ import annotations

import base64
import hashlib
import secrets
from html.parser import HTMLParser
from urllib.parse import parse_qs, urlparse

import pytest
import requests
from joserfc import jwt
from joserfc.jwk import KeySet

from tests.sign_in.oidc_provider import Provider, start_provider

REDIRECT_URI = "http://127.0.0.1:1/cb"
SCOPE = "openid email profile"
OLGA = {"sub": "olga", "email": "olga@plant.example", "name": "Olga Operator", "groups": ["lifecycle-operators"]}
TIMEOUT = 10


@pytest.fixture
def provider(tmp_path):
    started = start_provider(tmp_path / "oidc", [OLGA])
    yield started
    started.stop()


class _Forms(HTMLParser):
    """The forms of a page: each one's method and action, and its buttons' and inputs' names and values."""

    def __init__(self) -> None:
        super().__init__()
        self.forms: list[dict] = []

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag == "form":
            self.forms.append({"method": attrs.get("method", "get"), "action": attrs.get("action"), "fields": []})
        elif tag in ("button", "input") and self.forms and attrs.get("name"):
            self.forms[-1]["fields"].append((attrs["name"], attrs.get("value")))


def forms(html: str) -> list[dict]:
    parser = _Forms()
    parser.feed(html)
    return parser.forms


def pkce_pair() -> tuple[str, str]:
    verifier = secrets.token_urlsafe(48)
    challenge = base64.urlsafe_b64encode(hashlib.sha256(verifier.encode()).digest()).rstrip(b"=").decode()
    return verifier, challenge


def authorization_params(client_id: str, **extra: str) -> dict[str, str]:
    return {"response_type": "code", "client_id": client_id, "redirect_uri": REDIRECT_URI, "scope": SCOPE,
            "nonce": secrets.token_urlsafe(16), "state": secrets.token_urlsafe(16), **extra}


def redirect_query(response: requests.Response) -> dict[str, str]:
    """The query of the redirect back to the client (the provider's answer to the authorization)."""
    assert response.status_code == 302, f"{response.status_code}: {response.text[:500]}"
    location = response.headers["Location"]
    assert location.startswith(REDIRECT_URI + "?"), location
    return {name: values[0] for name, values in parse_qs(urlparse(location).query).items()}


def authorize(endpoints: dict[str, str], client_id: str, sub: str, **extra: str) -> tuple[dict, dict]:
    """The user ``sub`` chosen on the provider's form, as a browser would: (params sent, redirect query)."""
    params = authorization_params(client_id, **extra)
    page = requests.get(endpoints["authorization_endpoint"], params=params, timeout=TIMEOUT)
    assert page.status_code == 200, f"{page.status_code}: {page.text[:500]}"
    # The predefined users' form: one submit button per user, name "sub"; posted to the same URL.
    [users_form] = [form for form in forms(page.text) if ("sub", sub) in form["fields"]]
    assert users_form["method"] == "post" and users_form["action"] is None, users_form
    answer = requests.post(page.url, data={"sub": sub}, allow_redirects=False, timeout=TIMEOUT)
    query = redirect_query(answer)
    assert query["state"] == params["state"], query
    return params, query


def token_request(endpoints: dict[str, str], client: tuple[str, str], code: str, **extra: str) -> requests.Response:
    """The token request as mozilla-django-oidc makes it: client_id and client_secret in the body."""
    client_id, client_secret = client
    return requests.post(endpoints["token_endpoint"], data={
        "grant_type": "authorization_code", "code": code, "redirect_uri": REDIRECT_URI,
        "client_id": client_id, "client_secret": client_secret, **extra,
    }, timeout=TIMEOUT)


def verified_claims(provider: Provider, endpoints: dict[str, str], id_token: str) -> dict:
    keys = KeySet.import_key_set(requests.get(endpoints["jwks_uri"], timeout=TIMEOUT).json())
    token = jwt.decode(id_token, keys, algorithms=["RS256"])  # the signature checked
    jwt.JWTClaimsRegistry(iss={"essential": True, "value": provider.issuer}).validate(token.claims)
    return token.claims


def test_code_flow_with_pkce_gives_an_id_token_with_groups(provider):
    endpoints = provider.endpoints()
    assert set(endpoints) >= {"authorization_endpoint", "token_endpoint", "userinfo_endpoint", "jwks_uri",
                              "end_session_endpoint"}
    assert all(url.startswith(provider.issuer + "/") for url in endpoints.values()), endpoints
    client = provider.register_client(REDIRECT_URI)

    verifier, challenge = pkce_pair()
    params, query = authorize(endpoints, client[0], OLGA["sub"], code_challenge=challenge,
                              code_challenge_method="S256")
    response = token_request(endpoints, client, query["code"], code_verifier=verifier)
    assert response.status_code == 200, response.text
    tokens = response.json()

    claims = verified_claims(provider, endpoints, tokens["id_token"])
    assert claims["aud"] == [client[0]] and claims["nonce"] == params["nonce"], claims  # aud: a list
    assert {name: claims.get(name) for name in OLGA} == OLGA, claims  # sub, email, name, groups

    userinfo = requests.get(endpoints["userinfo_endpoint"], timeout=TIMEOUT,
                            headers={"Authorization": f"Bearer {tokens['access_token']}"})
    assert userinfo.status_code == 200, userinfo.text
    assert userinfo.json() == OLGA

    # The code is spent: a second exchange is refused.
    again = token_request(endpoints, client, query["code"], code_verifier=verifier)
    assert again.status_code == 400 and again.json()["error"] == "invalid_grant", again.text


def test_pkce_is_mandatory(provider):
    endpoints = provider.endpoints()
    client = provider.register_client(REDIRECT_URI)

    # (a) No code_challenge: refused at once (back to the client with an error, no form shown),
    # and so is the user's choice posted anyway.
    params = authorization_params(client[0])
    refused = requests.get(endpoints["authorization_endpoint"], params=params, allow_redirects=False,
                           timeout=TIMEOUT)
    query = redirect_query(refused)
    assert query["error"] == "invalid_request" and "code_challenge" in query["error_description"], query
    assert query["state"] == params["state"], query
    posted = requests.post(refused.request.url, data={"sub": OLGA["sub"]}, allow_redirects=False, timeout=TIMEOUT)
    assert "code" not in redirect_query(posted)
    # A "plain" challenge (or one without a method, which means plain) is refused too.
    verifier, challenge = pkce_pair()
    for method in ({"code_challenge_method": "plain"}, {}):
        plain = requests.get(endpoints["authorization_endpoint"], allow_redirects=False, timeout=TIMEOUT,
                             params=authorization_params(client[0], code_challenge=challenge, **method))
        assert redirect_query(plain)["error"] == "invalid_request", method

    # (b) A code issued with a challenge: a wrong verifier, or none, is refused.
    _, query = authorize(endpoints, client[0], OLGA["sub"], code_challenge=challenge, code_challenge_method="S256")
    wrong = token_request(endpoints, client, query["code"], code_verifier=pkce_pair()[0])
    assert wrong.status_code == 400 and wrong.json()["error"] == "invalid_grant", wrong.text
    missing = token_request(endpoints, client, query["code"])
    assert missing.status_code == 400 and missing.json()["error"] == "invalid_request", missing.text
    # A wrong client secret is refused whatever the verifier.
    bad_secret = token_request(endpoints, (client[0], "not the secret"), query["code"], code_verifier=verifier)
    assert bad_secret.status_code == 401 and bad_secret.json()["error"] == "invalid_client", bad_secret.text
    # (The refusals did not spend the code: the right verifier still gets the tokens.)
    assert token_request(endpoints, client, query["code"], code_verifier=verifier).status_code == 200


def test_end_session_confirms_on_a_form_then_redirects(provider):
    endpoints = provider.endpoints()
    page = requests.get(endpoints["end_session_endpoint"], timeout=TIMEOUT,
                        params={"post_logout_redirect_uri": "http://127.0.0.1:1/bye", "state": "s1"})
    assert page.status_code == 200, page.text
    [confirm] = [form for form in forms(page.text) if form["action"]]
    assert confirm["method"] == "post" and confirm["action"] == "/oauth2/end_session/confirm", confirm
    fields = {name: value for name, value in confirm["fields"] if value is not None}
    assert fields == {"redirect_uri": "http://127.0.0.1:1/bye?state=s1"}, confirm
    done = requests.post(provider.issuer + confirm["action"], data=fields, allow_redirects=False, timeout=TIMEOUT)
    assert done.status_code == 302 and done.headers["Location"] == "http://127.0.0.1:1/bye?state=s1", done.headers


def test_the_provider_comes_back_with_the_same_client_and_key(provider):
    endpoints = provider.endpoints()
    client = provider.register_client(REDIRECT_URI)
    jwks = requests.get(endpoints["jwks_uri"], timeout=TIMEOUT).json()

    provider.stop()
    with pytest.raises(requests.ConnectionError):
        provider.endpoints()

    provider.start()
    assert provider.endpoints() == endpoints
    assert requests.get(endpoints["jwks_uri"], timeout=TIMEOUT).json() == jwks
    verifier, challenge = pkce_pair()
    _, query = authorize(endpoints, client[0], OLGA["sub"], code_challenge=challenge, code_challenge_method="S256")
    response = token_request(endpoints, client, query["code"], code_verifier=verifier)
    assert response.status_code == 200, response.text
    assert verified_claims(provider, endpoints, response.json()["id_token"])["groups"] == ["lifecycle-operators"]

    # A client the provider never registered is refused (not let through as "any client").
    refused = requests.get(endpoints["authorization_endpoint"], allow_redirects=False, timeout=TIMEOUT,
                           params=authorization_params("unknown-client", code_challenge=challenge,
                                                       code_challenge_method="S256"))
    assert refused.status_code == 400 and "invalid_client" in refused.text, refused.text[:500]
