"""Security headers of the site's answers."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

from django.conf import settings
from django.test import Client, override_settings

from lifecycle_site.fleet.models import ManagedNode, Robot
from ros_gateway.shared import state_machine as sm
from tests.conftest import client_of, make_user


def test_pages_and_api_answers_are_not_stored_by_browsers(viewer_client):
    robot = Robot.objects.create(name="hdr-agv", domain_id=99)
    node = ManagedNode.objects.create(robot=robot, name="/lidar", alive=True, state_id=sm.UNCONFIGURED,
                                      state_label="unconfigured")
    for path in ("/", "/api/v1/nodes", f"/nodes/{node.key}/", "/audit/", "/login/"):
        header = viewer_client.get(path)["Cache-Control"]
        assert "no-store" in header and "private" in header, (path, header)
    assert "no-store" in Client().get("/api/v1/nodes")["Cache-Control"]  # the 401 too


PAGES = ("/", "/audit/", "/login/", "/admin/", "/api/v1/nodes")


def directives(policy: str) -> dict[str, list[str]]:
    parts = (part.split() for part in policy.split(";") if part.strip())
    return {words[0]: words[1:] for words in parts}


def test_every_page_has_a_strict_content_security_policy(db):
    client = client_of("ada-admin", "admin")
    for path in PAGES:
        answer = client.get(path)
        policy = directives(answer["Content-Security-Policy"])
        assert policy["script-src"] == ["'self'"], (path, policy)  # no inline script, no eval
        assert policy["style-src"] == ["'self'"], (path, policy)
        assert policy["default-src"] == ["'self'"] and policy["connect-src"] == ["'self'"], (path, policy)
        assert policy["object-src"] == ["'none'"] and policy["base-uri"] == ["'none'"], (path, policy)
        assert policy["frame-ancestors"] == ["'none'"] and policy["form-action"] == ["'self'"], (path, policy)
        assert answer["X-Content-Type-Options"] == "nosniff", path
        assert answer["Referrer-Policy"] == "same-origin", path
        assert answer["Cross-Origin-Opener-Policy"] == "same-origin", path
        assert answer["X-Frame-Options"] == "DENY", path


def test_templates_carry_no_inline_script_or_handler():
    """What the policy would block: <script> without src (JSON data blocks aside), on*="..."."""
    root = Path(settings.BASE_DIR) / "templates"
    for template in root.rglob("*.html"):
        text = template.read_text()
        assert not re.search(r"\son[a-z]+\s*=", text), template
        assert not re.search(r"hx-on|javascript:|\bjs:", text), template
        for tag in re.findall(r"<script\b[^>]*>", text):
            assert "src=" in tag, (template, tag)
        assert "style=" not in text and "<style" not in text, template


def site_settings(**env: str) -> dict:
    """The security settings a fresh process gets from lifecycle_site/settings.py with ``env``."""
    script = ("import json, lifecycle_site.settings as s; print(json.dumps({n: getattr(s, n, None) for n in "
              f"{sorted(TLS_SETTINGS)!r}}}))")
    environment = {k: v for k, v in os.environ.items() if not k.startswith(("LIFECYCLE_BEHIND", "LIFECYCLE_HSTS"))}
    answer = subprocess.run([sys.executable, "-c", script], env={**environment, **env}, capture_output=True,
                            text=True, timeout=120, cwd=settings.BASE_DIR, check=True)
    values = json.loads(answer.stdout)
    values["SECURE_PROXY_SSL_HEADER"] = tuple(values["SECURE_PROXY_SSL_HEADER"] or ()) or None
    return {name: TLS_SETTINGS[name] if value is None else value for name, value in values.items()}


# What each setting is when settings.py leaves it alone (Django's defaults).
TLS_SETTINGS = {"SECURE_PROXY_SSL_HEADER": None, "SECURE_HSTS_SECONDS": 0, "SECURE_HSTS_INCLUDE_SUBDOMAINS": False,
                "SESSION_COOKIE_SECURE": False, "CSRF_COOKIE_SECURE": False}


def logged_in(values: dict, **headers: str):
    """The login page, then the login form posted, under ``values``: both answers."""
    with override_settings(**values):
        client = Client(**headers)  # a new Client: the middleware reads the settings when it starts
        page = client.get("/login/")
        posted = client.post("/login/", {"username": "hanna-cookie", "password": "a-test-password-123",
                                         "csrfmiddlewaretoken": page.cookies[settings.CSRF_COOKIE_NAME].value})
    assert posted.status_code == 302, posted.status_code
    return page, posted


def test_hsts_and_secure_cookies_only_behind_a_tls_proxy(db):
    make_user("hanna-cookie", "viewer")
    plain = site_settings()
    for headers in ({}, {"HTTP_X_FORWARDED_PROTO": "https"}):  # nobody trusts that header here
        page, posted = logged_in(plain, **headers)
        assert "Strict-Transport-Security" not in page and "Strict-Transport-Security" not in posted, headers
        assert not page.cookies[settings.CSRF_COOKIE_NAME]["secure"], headers
        session = posted.cookies[settings.SESSION_COOKIE_NAME]
        assert not session["secure"] and session["httponly"] and session["samesite"] == "Lax", headers

    tls = site_settings(LIFECYCLE_BEHIND_TLS_PROXY="1")
    page, posted = logged_in(tls, HTTP_X_FORWARDED_PROTO="https")
    assert page["Strict-Transport-Security"] == "max-age=31536000"
    assert page.cookies[settings.CSRF_COOKIE_NAME]["secure"]
    session = posted.cookies[settings.SESSION_COOKIE_NAME]
    assert session["secure"] and session["httponly"] and session["samesite"] == "Lax"
    # The proxy's own health checks over plain HTTP: no HSTS on a plain answer.
    assert "Strict-Transport-Security" not in logged_in(tls)[0]

    tuned = site_settings(LIFECYCLE_BEHIND_TLS_PROXY="1", LIFECYCLE_HSTS_SECONDS="600",
                          LIFECYCLE_HSTS_INCLUDE_SUBDOMAINS="1")
    page, _ = logged_in(tuned, HTTP_X_FORWARDED_PROTO="https")
    assert page["Strict-Transport-Security"] == "max-age=600; includeSubDomains"
