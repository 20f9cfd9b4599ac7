"""API tokens without the command line: any logged-in user makes and revokes their own on the
"API tokens" page, admins in the admin (for accounts they may manage) and revoke anyone's; the
token is shown once, acts as its user and no more, and every creation and revocation is on
record for admins."""
from __future__ import annotations

import io
import re

import pytest
from django.contrib.auth import get_user_model
from django.core.management import call_command
from django.test import Client

from lifecycle_site.api.models import MAX_TOKENS_PER_USER, ApiToken, TokenEvent
from tests.conftest import make_user

TOKEN = re.compile(r'value="(lcm_[A-Za-z0-9_-]{20,})"')


def logged_in(user) -> Client:
    client = Client()
    client.force_login(user)
    return client


def api_status(token: str) -> int:
    return Client().get("/api/v1/robots", HTTP_AUTHORIZATION=f"Bearer {token}").status_code


def events() -> list[tuple]:
    return list(TokenEvent.objects.order_by("id").values_list("action", "owner_name", "actor_name", "via"))


def test_a_viewer_makes_a_token_sees_it_once_and_revokes_it(db):
    vera = make_user("vera-viewer", "viewer")
    client = logged_in(vera)
    assert "You have no tokens." in client.get("/tokens/").content.decode()
    made = client.post("/tokens/", {"name": "line PC dashboard"})
    assert made.status_code == 201 and "no-store" in made["Cache-Control"]
    token = TOKEN.search(made.content.decode())[1]
    assert "shown only this once" in made.content.decode()
    assert api_status(token) == 200
    # It acts as its user and no more: a viewer's token may not change anything.
    refused = Client().post("/api/v1/nodes/x.y/transition", {"transition": "configure"},
                            content_type="application/json", HTTP_AUTHORIZATION=f"Bearer {token}")
    assert refused.status_code == 403
    listing = client.get("/tokens/").content.decode()
    assert token not in listing and f"{token[:10]}…" in listing and "line PC dashboard" in listing

    record = ApiToken.objects.get(user=vera)
    done = client.post(f"/tokens/{record.pk}/revoke", follow=True)
    assert "revoked: it no longer works" in done.content.decode()
    assert api_status(token) == 401
    assert events() == [("created", "vera-viewer", "vera-viewer", "API tokens page"),
                        ("revoked", "vera-viewer", "vera-viewer", "API tokens page")]


def test_a_user_cannot_see_or_revoke_another_users_token(db):
    olga, vera = make_user("olga-operator", "operator"), make_user("vera-viewer", "viewer")
    record, token = ApiToken.issue(olga, "olga's robot script", by=olga)
    client = logged_in(vera)
    page = client.get("/tokens/").content.decode()
    assert "robot script" not in page and record.hint not in page
    assert client.post(f"/tokens/{record.pk}/revoke").status_code == 404
    assert client.get(f"/tokens/{record.pk}/revoke").status_code == 405
    assert api_status(token) == 200


def test_an_account_without_a_role_may_make_one_that_can_do_nothing(db):
    nobody = make_user("new-hire", None)
    made = logged_in(nobody).post("/tokens/", {"name": "try"})
    assert "has no role yet" in made.content.decode()
    assert api_status(TOKEN.search(made.content.decode())[1]) == 403


def test_a_token_needs_a_name_and_an_account_has_a_bounded_number(db):
    vera = make_user("vera-viewer", "viewer")
    client = logged_in(vera)
    assert "Name the token" in client.post("/tokens/", {"name": "  "}).content.decode()
    for i in range(MAX_TOKENS_PER_USER):
        ApiToken.issue(vera, f"t{i}", by=vera)
    refused = client.post("/tokens/", {"name": "one more"})
    assert refused.status_code == 400 and "revoke one that is no longer used" in refused.content.decode()
    assert ApiToken.objects.filter(user=vera).count() == MAX_TOKENS_PER_USER
    assert Client().get("/tokens/").status_code == 302  # login first


@pytest.fixture
def ada(db):
    return make_user("ada-admin", "admin")


def test_an_admin_makes_a_token_for_an_operator_in_the_admin_and_it_is_shown_once(ada):
    olga = make_user("olga-operator", "operator")
    client = logged_in(ada)
    form = client.get("/admin/api/apitoken/add/").content.decode()
    assert f'<option value="{olga.pk}">olga-operator</option>' in form
    made = client.post("/admin/api/apitoken/add/", {"user": olga.pk, "name": "CI bring-up"})
    assert made.status_code == 200, made.content.decode()[:2000]
    token = TOKEN.search(made.content.decode())[1]
    assert "shown only this once" in made.content.decode()
    assert api_status(token) == 200
    assert ApiToken.objects.get(user=olga).name == "CI bring-up"
    assert token not in client.get("/admin/api/apitoken/").content.decode()
    assert events() == [("created", "olga-operator", "ada-admin", "admin")]


def test_an_admin_cannot_make_a_token_for_a_superuser_or_another_admin(ada):
    root = get_user_model().objects.create_superuser("sam-super", "sam@plant.example", "pw-123-456-789")
    other = make_user("adam-admin", "admin")
    client = logged_in(ada)
    for target in (root, other):
        answer = client.post("/admin/api/apitoken/add/", {"user": target.pk, "name": "act as them"})
        assert "Select a valid choice" in answer.content.decode()
    assert not ApiToken.objects.exists()
    # A superuser may (service accounts).
    made = logged_in(root).post("/admin/api/apitoken/add/", {"user": other.pk, "name": "ops"})
    assert TOKEN.search(made.content.decode())


def test_an_admin_revokes_anyones_token_and_reviews_the_record(ada):
    olga = make_user("olga-operator", "operator")
    record, token = ApiToken.issue(olga, "CI", by=olga, via="API tokens page")
    client = logged_in(ada)
    done = client.post(f"/admin/api/apitoken/{record.pk}/delete/", {"post": "yes"})
    assert done.status_code == 302
    assert api_status(token) == 401
    second, _ = ApiToken.issue(olga, "CI 2", by=olga)
    client.post("/admin/api/apitoken/", {"action": "delete_selected", "_selected_action": [second.pk], "post": "yes"})
    assert not ApiToken.objects.exists()
    listing = client.get("/admin/api/tokenevent/").content.decode()
    assert listing.count("ada-admin") >= 2 and "revoked" in listing
    assert [e for e in events() if e[0] == "revoked"] == [("revoked", "olga-operator", "ada-admin", "admin")] * 2
    # The record is read-only, and out of reach of viewers and operators.
    event = TokenEvent.objects.first()
    assert client.post(f"/admin/api/tokenevent/{event.pk}/delete/", {"post": "yes"}).status_code == 403
    assert logged_in(olga).get("/admin/api/tokenevent/").status_code == 302


def test_the_command_line_token_is_on_record_too(db):
    make_user("cli-user", "operator")
    out = io.StringIO()
    call_command("create_api_token", "cli-user", "--name", "cron", stdout=out, stderr=io.StringIO())
    assert api_status(out.getvalue().strip()) == 200
    assert events() == [("created", "cli-user", "", "command line")]


def test_deleting_a_user_puts_the_revocation_of_their_tokens_on_record(db):
    root = get_user_model().objects.create_superuser("root-admin", password="a long root password 1")
    olga = make_user("olga-operator", "operator")
    _, token = ApiToken.issue(olga, "CI", by=olga, via="API tokens page")
    done = logged_in(root).post(f"/admin/auth/user/{olga.pk}/delete/", {"post": "yes"})
    assert done.status_code == 302 and not get_user_model().objects.filter(username="olga-operator").exists()
    assert api_status(token) == 401
    assert events() == [("created", "olga-operator", "olga-operator", "API tokens page"),
                        ("revoked", "olga-operator", "", "deleted with its user")]
    assert set(TokenEvent.objects.values_list("owner", flat=True)) == {None}  # the user's row is gone


def test_a_directory_accounts_token_works_for_a_while_after_its_last_sign_in(db, settings):
    """The directory is not asked when a token is used: a company account's tokens stop working
    LIFECYCLE_DIRECTORY_TOKEN_DAYS after its last sign-in (a person who left, or lost the group),
    say why, are on record, and work again once it signs in. A local account's are not bounded."""
    from datetime import timedelta

    from django.utils import timezone

    from lifecycle_site.api import grants
    from lifecycle_site.audit.models import AccessDenial
    from lifecycle_site.sign_in.models import DirectoryAccount

    settings.LIFECYCLE_DIRECTORY_TOKEN_DAYS = 30
    olga = make_user("olga.k", "operator")
    account = DirectoryAccount.objects.create(user=olga, source=DirectoryAccount.LDAP, subject="olga.k",
                                              role="operator", last_sign_in=timezone.now() - timedelta(days=29))
    _, token = ApiToken.issue(olga, "line PC")
    _, local_token = ApiToken.issue(make_user("line-pc", "viewer"), "kiosk")
    ApiToken.objects.filter(user__username="line-pc").update(created=timezone.now() - timedelta(days=400))
    assert api_status(token) == 200

    account.last_sign_in = timezone.now() - timedelta(days=31)
    account.save()
    grants.forget()  # (another process's change: within the grants' few seconds)
    answer = Client().get("/api/v1/robots", HTTP_AUTHORIZATION=f"Bearer {token}")
    assert answer.status_code == 401 and answer.json()["error"]["code"] == "token_dormant"
    assert "olga.k, a company account that has not signed in here for 30 days" in answer.json()["error"]["message"]
    denial = AccessDenial.objects.order_by("-id").first()
    assert (denial.code, denial.status) == ("token_dormant", 401) and "olga.k" in denial.detail
    assert api_status(local_token) == 200

    signed_in = timezone.now()
    DirectoryAccount.objects.filter(pk=account.pk).update(last_sign_in=signed_in)  # she signs in
    grants.forget()
    assert api_status(token) == 200
    until = (signed_in + timedelta(days=30)).strftime("%Y-%m-%d %H:%M")
    assert f"its tokens work until {until} UTC, 30 days after your last sign-in" in \
        logged_in(olga).get("/tokens/").content.decode()
    assert "company directory" not in logged_in(get_user_model().objects.get(username="line-pc")).get(
        "/tokens/").content.decode()
