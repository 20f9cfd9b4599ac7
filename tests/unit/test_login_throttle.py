"""Brute force: wrong passwords are counted per account and per client address; past the
limit the login is refused (the right password too) with a page that says so and for how
long; the admin login is guarded the same way; every failure is on record with the name."""
from __future__ import annotations

from datetime import datetime, timedelta

from django.db.models import F
from django.test import Client
from django.utils import timezone

from lifecycle_site.audit.models import AccessDenial
from tests.conftest import make_user

PASSWORD = "a-test-password-123"


def login(client: Client, username: str, password: str, address: str = "10.0.0.1", path: str = "/login/"):
    return client.post(path, {"username": username, "password": password}, REMOTE_ADDR=address)


def test_five_wrong_passwords_lock_the_account_and_say_so(db):
    make_user("olga-operator", "operator")
    for attempt in range(4):
        assert login(Client(), "olga-operator", f"guess-{attempt}", f"10.0.0.{attempt + 1}").status_code == 200
    assert login(Client(), "olga-operator", "guess-4", "10.0.0.5").status_code == 429  # the fifth: blocked
    refused = login(Client(), "olga-operator", PASSWORD, "10.0.0.99")  # the right one, from elsewhere
    assert refused.status_code == 429
    page = refused.content.decode()
    assert "Login blocked" in page and "olga-operator" in page and "15 minutes" in page
    assert "_auth_user_id" not in Client().session
    codes = list(AccessDenial.objects.filter(username="olga-operator").order_by("id").values_list("code", flat=True))
    assert codes == ["login_failed"] * 4 + ["login_blocked"] * 2, codes  # the fifth wrong one sets the block


def test_one_address_trying_many_accounts_is_blocked_too(db):
    for name in ("u1", "u2", "u3", "u4", "u5"):
        login(Client(), name, "wrong", "10.6.6.6")
    make_user("victor-viewer", "viewer")
    assert login(Client(), "victor-viewer", PASSWORD, "10.6.6.6").status_code == 429
    assert login(Client(), "victor-viewer", PASSWORD, "10.7.7.7").status_code == 302  # others are not


def test_a_right_password_before_the_limit_resets_the_count(db):
    make_user("olga-operator", "operator")
    for _ in range(4):
        login(Client(), "olga-operator", "wrong")
    assert login(Client(), "olga-operator", PASSWORD).status_code == 302
    for _ in range(4):
        login(Client(), "olga-operator", "wrong")
    assert login(Client(), "olga-operator", PASSWORD).status_code == 302


def test_a_good_login_of_another_account_does_not_wipe_the_failures(db):
    """An account holder guessing another account's password: 4 guesses, then a good login of
    their own account from the same address, over and over. The guesses still add up."""
    make_user("admin1", "admin")
    make_user("viewer1", "viewer")
    answers = []
    for _round in range(5):
        answers += [login(Client(), "admin1", f"guess-{len(answers)}", "10.4.4.4").status_code for _ in range(4)]
        login(Client(), "viewer1", PASSWORD, "10.4.4.4")
    refused = answers.count(429)
    assert answers == [200] * 4 + [429] * 16, f"{refused} of 20 guesses refused: {answers}"  # the fifth blocks
    assert login(Client(), "admin1", PASSWORD, "10.4.4.5").status_code == 429  # the account is blocked
    assert login(Client(), "viewer1", PASSWORD, "10.4.4.4").status_code == 429  # and so is the address


def test_a_good_login_does_not_wipe_the_addresss_failures_at_other_accounts(db):
    make_user("viewer1", "viewer")
    for name in ("u1", "u2", "u3", "u4"):  # one guess each: no account comes near its limit
        login(Client(), name, "wrong", "10.3.3.3")
    assert login(Client(), "viewer1", PASSWORD, "10.3.3.3").status_code == 302
    login(Client(), "u5", "wrong", "10.3.3.3")  # the address's fifth failure
    assert login(Client(), "viewer1", PASSWORD, "10.3.3.3").status_code == 429


def test_a_good_login_clears_the_users_own_mistypes_not_guesses_from_elsewhere(db):
    make_user("olga-operator", "operator")
    for _ in range(3):
        login(Client(), "olga-operator", "guess", "10.8.8.8")  # someone else, elsewhere
    login(Client(), "olga-operator", "mistyped", "10.0.0.1")  # olga herself
    assert login(Client(), "olga-operator", PASSWORD, "10.0.0.1").status_code == 302
    login(Client(), "olga-operator", "guess", "10.8.8.8")  # 4 counted against the account
    assert login(Client(), "olga-operator", PASSWORD, "10.0.0.1").status_code == 302
    login(Client(), "olga-operator", "guess", "10.8.8.8")  # the fifth guess
    assert login(Client(), "olga-operator", PASSWORD, "10.0.0.1").status_code == 429


def test_the_admin_login_is_guarded_alike(db):
    admin = make_user("ada-admin", "admin")
    admin.is_staff = True
    admin.save()
    for _ in range(5):
        login(Client(), "ada-admin", "wrong", path="/admin/login/")
    assert login(Client(), "ada-admin", PASSWORD, path="/admin/login/").status_code == 429


def test_an_address_blocked_for_bad_tokens_is_refused_every_token_until_the_block_ends(db):
    from lifecycle_site.api.models import ApiToken

    _record, token = ApiToken.issue(make_user("tess-token", "viewer"), "ci")
    guesser = Client(REMOTE_ADDR="10.5.5.5")
    answers = [guesser.get("/api/v1/nodes", HTTP_AUTHORIZATION=f"Bearer guess-{i}").status_code for i in range(21)]
    assert answers == [401] * 20 + [429]
    # Blocked means blocked: a valid token from there is refused too, unchecked.
    valid = guesser.get("/api/v1/nodes", HTTP_AUTHORIZATION=f"Bearer {token}")
    assert valid.status_code == 429, f"a valid token from the blocked address got {valid.status_code}"
    guesser.get("/api/v1/nodes", HTTP_AUTHORIZATION="Bearer guess-22")
    rows = list(AccessDenial.objects.filter(client="10.5.5.5").order_by("id").values_list("code", "status"))
    assert rows == [("bad_token", 401)] * 20 + [("token_blocked", 429)] * 3, rows  # every refusal on record
    error = valid.json()["error"]
    first = AccessDenial.objects.filter(code="bad_token").order_by("id").values_list("at", flat=True).first()
    until = first + timedelta(minutes=15)  # the first of the 20 leaves the lock-out time
    assert error["code"] == "too_many_attempts" and datetime.fromisoformat(error["until"]) == until
    assert 0 < error["retry_after"] <= 15 * 60 and valid["Retry-After"] == str(error["retry_after"])
    # Other addresses are not affected.
    assert Client(REMOTE_ADDR="10.5.5.6").get("/api/v1/nodes", HTTP_AUTHORIZATION=f"Bearer {token}").status_code == 200
    assert Client(REMOTE_ADDR="10.5.5.6").get("/api/v1/nodes", HTTP_AUTHORIZATION="Bearer guess").status_code == 401
    # The block ends when the first of the 20 leaves the lock-out time: as if that time came now.
    first_row = AccessDenial.objects.filter(code="bad_token", at=first)
    first_row.update(at=F("at") - (until - timezone.now()) - timedelta(seconds=1))
    assert guesser.get("/api/v1/nodes", HTTP_AUTHORIZATION=f"Bearer {token}").status_code == 200
    assert guesser.get("/api/v1/nodes", HTTP_AUTHORIZATION="Bearer guess-23").status_code == 401  # 20 again
    assert guesser.get("/api/v1/nodes", HTTP_AUTHORIZATION=f"Bearer {token}").status_code == 429
