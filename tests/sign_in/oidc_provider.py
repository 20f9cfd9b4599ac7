"""A real OpenID Connect provider for tests, in a process of its own: oidc-provider-mock (Flask +
authlib, authorization code flow, dynamic client registration, users picked on a form), with
PKCE (S256) made mandatory, which the package itself does not check.

Run as a process (``start_provider`` does it)::

    python -m tests.sign_in.oidc_provider --port P --users-json FILE [--clients-json FILE] [--key-file FILE]

``--users-json``: a list of ``{"sub": ..., "email": ..., "name": ..., "groups": [...]}``; every key
but ``sub`` becomes a claim. Standard claims reach the ID token and userinfo only under their
scope (``email`` under "email", ``name`` under "profile"); non-standard ones (``groups``) under any.
``--clients-json`` and ``--key-file`` keep what the package holds in memory only (registered
clients, the signing key) across a restart of the process, as a real provider would.

The issuer is ``http://127.0.0.1:P``, taken by the package from each request's Host: use
127.0.0.1, never "localhost", or the issuer (and every endpoint URL) differs.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
import warnings
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from tests import stack

HOST = "127.0.0.1"
START_TIMEOUT = 15.0
REQUEST_TIMEOUT = 5.0
ENDPOINT_NAMES = ("authorization_endpoint", "token_endpoint", "userinfo_endpoint", "jwks_uri",
                  "end_session_endpoint")


# --- The provider process ---------------------------------------------------------------------

def _mandatory_pkce():
    """authlib's PKCE extension for the authorization code grant, made mandatory for every client.

    ``CodeChallenge(required=True)`` alone is not enough here: authlib demands PKCE only of public
    clients (token_endpoint_auth_method "none"), and only at the token endpoint; an authorization
    request without ``code_challenge`` passes. And it reads the challenge back from the stored code
    (``code.code_challenge``), which oidc-provider-mock's frozen ``AuthorizationCode`` has no field
    for. So: refuse an authorization request without an S256 challenge, keep each code's challenge
    beside it here (in memory, like the package's own codes), and read it back at the token
    endpoint, where authlib then demands a matching ``code_verifier`` (a code always has a
    challenge now).
    """
    from authlib.oauth2.rfc6749 import InvalidRequestError
    from authlib.oauth2.rfc7636 import CodeChallenge

    class MandatoryCodeChallenge(CodeChallenge):
        SUPPORTED_CODE_CHALLENGE_METHOD = ["S256"]

        def __init__(self) -> None:
            super().__init__(required=True)
            self.challenges: dict[str, tuple[str, str]] = {}  # code -> (challenge, method)

        def __call__(self, grant) -> None:
            super().__call__(grant)  # its hooks at the authorization and at the token endpoint
            save = grant.save_authorization_code  # the package's; this grant instance's only
            grant.save_authorization_code = partial(self._save, save)

        def _save(self, save, code: str, request) -> None:
            save(code, request)
            data = request.payload.data
            self.challenges[code] = (data["code_challenge"], data["code_challenge_method"])

        def validate_code_challenge(self, grant, redirect_uri) -> None:
            data = grant.request.payload.data
            if not data.get("code_challenge"):
                raise InvalidRequestError("Missing 'code_challenge': this provider requires PKCE")
            if data.get("code_challenge_method") != "S256":  # absent means "plain" (RFC 7636 4.3)
                raise InvalidRequestError("'code_challenge_method' must be S256")
            super().validate_code_challenge(grant, redirect_uri)

        def get_authorization_code_challenge(self, authorization_code):
            return self.challenges.get(authorization_code.code, (None, None))[0]

        def get_authorization_code_challenge_method(self, authorization_code):
            return self.challenges.get(authorization_code.code, (None, None))[1]

    return MandatoryCodeChallenge()


def _name_the_key_in_id_tokens() -> None:
    """ID tokens carry the signing key's ``kid`` in their header, as a real provider's do (the
    package's leave it out; authlib puts it in when the grant's JWT config names it)."""
    from oidc_provider_mock import _app

    if getattr(_app.OpenIDCode.get_jwt_config, "names_kid", False):
        return
    original = _app.OpenIDCode.get_jwt_config

    def get_jwt_config(self, grant, client=None):
        config = original(self, grant, client)
        config["kid"] = config["key"].get("kid")
        return config

    get_jwt_config.names_kid = True
    _app.OpenIDCode.get_jwt_config = get_jwt_config


def build_app(users: list[dict], clients: list[dict] | None = None, key_file: Path | None = None):
    """oidc-provider-mock's own app, nonce required, the users predefined, PKCE mandatory."""
    import flask
    import oidc_provider_mock
    from authlib import jose
    from authlib.oauth2.rfc6749 import AuthorizationCodeGrant
    from oidc_provider_mock._storage import Client  # the package's client record (no public API)

    app = oidc_provider_mock.app(
        require_client_registration=True,  # an unknown client_id is refused, as by a real provider
        require_nonce=True,
        user_claims=[oidc_provider_mock.User(sub=user["sub"], claims={k: v for k, v in user.items() if k != "sub"})
                     for user in users],
    )
    # The package keeps its AuthorizationServer and Storage in a closure and hands them to each
    # request through flask.g (before_request): a request context of our own reaches the same ones.
    with app.test_request_context():
        app.preprocess_request()
        server = flask.g._authlib_authorization_server
        storage = flask.g.oidc_provider_mock_storage

    # register_grant(grant_cls, extensions) stores (grant_cls, extensions) in both
    # _authorization_grants and _token_grants, and builds each request's grant with those
    # extensions; authlib has no public way to extend a grant already registered (registering it
    # again would not do: the first registration found wins), so the extension goes into the
    # registered list itself, both endpoints' entries.
    pkce = _mandatory_pkce()
    found = False
    for grant_cls, extensions in server._authorization_grants + server._token_grants:
        if issubclass(grant_cls, AuthorizationCodeGrant):
            found = True
            if extensions is None:  # the package passes a list ([OpenIDCode(...)]); None could not grow
                raise RuntimeError("oidc-provider-mock registered its code grant without extensions: PKCE not added")
            if not any(e is pkce for e in extensions):  # one list, in both endpoints' entries
                extensions.append(pkce)
    if not found:
        raise RuntimeError("oidc-provider-mock registered no authorization code grant: PKCE not enforced")

    for client in clients or []:  # registered with the process before this one (see Provider.start)
        storage.store_client(Client(
            id=client["client_id"], secret=client["client_secret"], redirect_uris=list(client["redirect_uris"]),
            allowed_scopes=Client.SCOPES_SUPPORTED, token_endpoint_auth_method=client["token_endpoint_auth_method"],
        ))

    # The signing key (the package makes a new one per process), with a key id: the package's has
    # none, and relying parties (mozilla-django-oidc among them) pick the JWKS key by the token's kid.
    key = storage.jwk.as_dict(is_private=True)
    if key_file is not None and key_file.exists():
        key = json.loads(key_file.read_text())
    key.setdefault("kid", "test-signing-key")
    storage.jwk = jose.RSAKey.import_key(key)
    _name_the_key_in_id_tokens()
    if key_file is not None and not key_file.exists():
        key_file.write_text(json.dumps(key))
        key_file.chmod(0o600)
    return app


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--users-json", type=Path, required=True)
    parser.add_argument("--clients-json", type=Path, help="clients to know from the start (Provider keeps it)")
    parser.add_argument("--key-file", type=Path, help="the signing key (JWK), written if absent")
    args = parser.parse_args(argv)

    # authlib refuses plain http unless this is set; the package's own __main__ sets it too
    # (loopback only, in tests).
    os.environ["AUTHLIB_INSECURE_TRANSPORT"] = "1"
    # authlib's warnings that its jose module (the package's, and the key's type) and its httpx
    # client are deprecated: noise in the log. Importing authlib.deprecate sets "always" for them,
    # so this filter comes after it.
    from authlib.deprecate import AuthlibDeprecationWarning

    warnings.simplefilter("ignore", AuthlibDeprecationWarning)
    # The records start with the date: the test run's conftest finds the errors in this log.
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    users = json.loads(args.users_json.read_text())
    clients = json.loads(args.clients_json.read_text()) if args.clients_json and args.clients_json.exists() else []
    app = build_app(users, clients, args.key_file)
    logging.getLogger(__name__).info("OIDC provider: %d users, %d clients known", len(users), len(clients))

    import uvicorn

    uvicorn.run(app, interface="wsgi", host=HOST, port=args.port, log_config=None)


# --- The tests' side --------------------------------------------------------------------------

@dataclass
class Provider:
    """A provider process on ``issuer``, its state under ``workdir``. ``stop()`` and ``start()``
    bring the same provider down and up on the same port: the registered clients and the signing
    key survive (files under ``workdir``); authorization codes and tokens do not."""

    issuer: str  # "http://127.0.0.1:P"
    process: stack.Process
    workdir: Path
    argv: list[str] = field(repr=False)
    env: dict[str, str] = field(repr=False)

    @property
    def clients_file(self) -> Path:
        return self.workdir / "clients.json"

    def endpoints(self) -> dict[str, str]:
        """The endpoints the provider's discovery document names (and its registration endpoint)."""
        import requests

        response = requests.get(f"{self.issuer}/.well-known/openid-configuration", timeout=REQUEST_TIMEOUT)
        response.raise_for_status()
        document = response.json()
        assert document["issuer"] == self.issuer, document["issuer"]
        return {name: document[name] for name in (*ENDPOINT_NAMES, "registration_endpoint")}

    def register_client(self, redirect_uri: str,
                        token_endpoint_auth_method: str = "client_secret_post") -> tuple[str, str]:
        """A new client through the provider's dynamic registration endpoint: (client_id, secret).

        "client_secret_post" by default: mozilla-django-oidc sends client_id and client_secret in
        the token request's body unless OIDC_TOKEN_USE_BASIC_AUTH (then "client_secret_basic").
        The provider holds exactly the auth method registered: another one is refused."""
        import requests

        response = requests.post(
            self.endpoints()["registration_endpoint"],
            json={"redirect_uris": [redirect_uri], "token_endpoint_auth_method": token_endpoint_auth_method},
            timeout=REQUEST_TIMEOUT,
        )
        assert response.status_code == 201, f"client registration: {response.status_code} {response.text}"
        client = response.json()
        # The provider matches redirect URIs exactly, after pydantic normalised them
        # ("http://host:1" becomes "http://host:1/"): say so here rather than at sign-in.
        assert client["redirect_uris"] == [redirect_uri], (
            f"the provider registered {client['redirect_uris']} for {redirect_uri!r}")
        clients = json.loads(self.clients_file.read_text()) if self.clients_file.exists() else []
        clients.append({key: client[key] for key in
                        ("client_id", "client_secret", "redirect_uris", "token_endpoint_auth_method")})
        self.clients_file.write_text(json.dumps(clients, indent=1))  # for the process after a restart
        return client["client_id"], client["client_secret"]

    def stop(self) -> None:
        """The provider down (connections refused on its port) until ``start()``."""
        self.process.stop()

    def start(self) -> None:
        """The provider up again on the same port, knowing the same users, clients and key; back
        when its discovery document answers (at most START_TIMEOUT seconds)."""
        from tests import stack

        assert not self.process.alive(), "the provider is running already"
        self.process = stack.Process(self.process.name, self.argv, self.env, stack.log_dir())
        self._wait_until_up()

    def _wait_until_up(self) -> None:
        import requests

        deadline = time.monotonic() + START_TIMEOUT
        last_error: Exception | None = None
        while time.monotonic() < deadline and self.process.alive():
            try:
                if requests.get(f"{self.issuer}/.well-known/openid-configuration", timeout=1).ok:
                    return
            except requests.RequestException as exc:
                last_error = exc
            time.sleep(0.05)
        state = "running" if self.process.alive() else f"exited with {self.process.popen.returncode}"
        self.process.kill()
        tail = "\n".join(self.process.output().splitlines()[-20:])
        raise AssertionError(
            f"the OIDC provider on {self.issuer} did not answer its discovery URL within {START_TIMEOUT:g} s "
            f"({state}; last error: {last_error}); its log: {self.process.log_path}\n{tail}")


def start_provider(workdir: Path, users: list[dict]) -> Provider:
    """A provider process on a free loopback port knowing ``users`` (see --users-json); its
    state files under ``workdir``, its log in the test run's log directory (shown on failure)."""
    from tests import stack

    workdir.mkdir(parents=True, exist_ok=True)
    port = stack.free_port()
    users_file = workdir / "users.json"
    users_file.write_text(json.dumps(users, indent=1))
    argv = [
        sys.executable, "-m", "tests.sign_in.oidc_provider", "--port", str(port),
        "--users-json", str(users_file), "--clients-json", str(workdir / "clients.json"),
        "--key-file", str(workdir / "jwk.json"),
    ]
    env = stack.environment(AUTHLIB_INSECURE_TRANSPORT="1", NO_COLOR="1")
    provider = Provider(
        issuer=f"http://{HOST}:{port}",
        process=stack.Process(f"oidc-provider-{port}", argv, env, stack.log_dir()),
        workdir=workdir, argv=argv, env=env,
    )
    provider._wait_until_up()
    return provider


if __name__ == "__main__":
    main()
