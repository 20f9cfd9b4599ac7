"""Only the site's own pages open its live sockets: a page of another origin (another port of
the same host included) that opens ws://site/ws/... with the user's cookie is refused, and the
refusal is on record. The site's real ASGI application, session middleware, consumers and Redis."""
from __future__ import annotations

import pytest
from asgiref.sync import async_to_sync
from channels.testing import WebsocketCommunicator
from django.conf import settings
from django.test import override_settings

from lifecycle_site.asgi import application
from lifecycle_site.audit.models import AccessDenial
from tests.conftest import make_user, session_of

SITE = "127.0.0.1:8000"


@pytest.fixture
def cookie(transactional_db, redis_server) -> str:
    session = session_of(make_user("olga-origin", "operator"))
    return f"{settings.SESSION_COOKIE_NAME}={session.session_key}"


def opens(cookie: str, origin: str | None, host: str = SITE, **headers: str) -> bool:
    """Whether /ws/fleet/ opened for a browser on ``origin`` with the user's cookie."""
    sent = [(b"host", host.encode()), (b"cookie", cookie.encode())]
    sent += [(name.replace("_", "-").encode(), value.encode()) for name, value in headers.items()]
    if origin is not None:
        sent.append((b"origin", origin.encode()))

    async def attempt() -> bool:
        communicator = WebsocketCommunicator(application, "/ws/fleet/", headers=sent)
        communicator.scope["client"] = ("192.0.2.7", 50123)
        connected, _ = await communicator.connect(timeout=10)
        # The browser's goodbye, as daphne sends it: an open consumer ends by itself (cancelled
        # at the loop's end inside a Redis channel read, it may never return); a refused socket's
        # application has ended already.
        await communicator.disconnect(timeout=10)
        return connected

    return async_to_sync(attempt)()


def test_a_page_of_another_port_on_the_same_host_is_refused_and_on_record(cookie):
    assert not opens(cookie, "http://127.0.0.1:9999"), "a page on another port read the live fleet"
    denial = AccessDenial.objects.get()
    assert (denial.code, denial.status, denial.username, denial.client) == ("socket_origin", 403, "olga-origin",
                                                                            "192.0.2.7")
    assert denial.path == "/ws/fleet/" and "http://127.0.0.1:9999" in denial.detail and SITE in denial.detail


def test_the_sites_own_page_opens_its_socket(cookie):
    assert opens(cookie, f"http://{SITE}")
    assert opens(cookie, "http://localhost", host="localhost:80")  # default port written or not
    assert not AccessDenial.objects.exists()


@pytest.mark.parametrize("origin", [f"https://{SITE}", "http://127.0.0.1", "http://localhost:8000",
                                    "null", "", None, "http://127.0.0.1:99999"])
def test_any_other_origin_is_refused(cookie, origin):
    assert not opens(cookie, origin)
    assert AccessDenial.objects.filter(code="socket_origin").count() == 1


def test_a_host_name_the_site_does_not_serve_is_refused_even_from_its_own_origin(cookie):
    """DNS rebinding: evil.example resolved to the site's address."""
    assert not opens(cookie, "http://evil.example:8000", host="evil.example:8000")


def test_behind_a_tls_proxy_the_https_page_opens_its_socket(cookie):
    with override_settings(SECURE_PROXY_SSL_HEADER=("HTTP_X_FORWARDED_PROTO", "https"),
                           ALLOWED_HOSTS=["edge.plant.example"]):
        assert opens(cookie, "https://edge.plant.example", host="edge.plant.example", x_forwarded_proto="https")
        assert not opens(cookie, "https://edge.plant.example", host="edge.plant.example")  # not said by the proxy
        assert not opens(cookie, "http://edge.plant.example", host="edge.plant.example", x_forwarded_proto="https")


def test_csrf_trusted_origins_may_open_sockets_too(cookie):
    """A proxy that rewrites the Host header: the operator lists the public origin."""
    with override_settings(CSRF_TRUSTED_ORIGINS=["https://hmi.plant.example", "https://*.cell.example"]):
        assert opens(cookie, "https://hmi.plant.example")
        assert opens(cookie, "https://panel-3.cell.example")
        assert not opens(cookie, "http://hmi.plant.example")
        assert not opens(cookie, "https://cell.example.evil.example")
