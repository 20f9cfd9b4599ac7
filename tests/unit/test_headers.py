"""Security headers of the site's answers."""
from __future__ import annotations

import re
from pathlib import Path

from django.conf import settings
from django.test import Client

from lifecycle_site.fleet.models import ManagedNode, Robot
from ros_gateway.shared import state_machine as sm
from tests.conftest import make_user


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
    client = Client()
    client.force_login(make_user("ada-admin", "admin"))
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
