"""Signing in with the company directory: a real OpenLDAP (Debian's slapd, started by the test)
over StartTLS and LDAPS, the real login page and backends. Roles come from the directory's
groups at every sign-in; refusals are in words and on record; a down or frozen directory is a
bounded refusal, not a hang; local accounts are never taken over and still work."""
from __future__ import annotations

import time

import pytest
from django.conf import settings
from django.contrib.auth import get_user_model
from django.test import Client, override_settings

from lifecycle_site.audit.models import AccessDenial
from lifecycle_site.sign_in import config, problems
from lifecycle_site.sign_in.models import DirectoryAccount
from tests import stack
from tests.conftest import make_user
from tests.sign_in.slapd import Directory, start_directory

ROLES = "viewer=plant-staff;operator=lifecycle-operators;admin=plant-it"
TIMEOUT_S = 2
PASSWORD = "correct horse battery staple"


@pytest.fixture(scope="module")
def directory(tmp_path_factory) -> Directory:
    directory = start_directory(tmp_path_factory.mktemp("slapd"))
    try:
        yield directory
    finally:
        directory.stop()


def directory_settings(directory: Directory, *, url: str | None = None, ca_file: str | None = None,
                       **more: str):
    """The site's settings for ``directory``, read from environment variables as in production
    (``more``: other LIFECYCLE_LDAP_* variables)."""
    ldap = config.ldap_settings({
        "LIFECYCLE_LDAP_URL": url or directory.url, "LIFECYCLE_LDAP_CA_FILE": ca_file or directory.ca_file,
        "LIFECYCLE_LDAP_USER_BASE": directory.people, "LIFECYCLE_LDAP_GROUP_BASE": directory.groups,
        "LIFECYCLE_LDAP_ROLES": ROLES, "LIFECYCLE_LDAP_TIMEOUT": str(TIMEOUT_S), **more})
    return override_settings(**ldap, LDAP_ON=True, AUTHENTICATION_BACKENDS=[
        "axes.backends.AxesStandaloneBackend", "django.contrib.auth.backends.ModelBackend",
        "lifecycle_site.sign_in.ldap.Backend"])


def log_in(username: str, password: str = PASSWORD) -> tuple[Client, object]:
    client = Client()
    return client, client.post("/login/", {"username": username, "password": password})


def refused_with(answer, problem: problems.Problem) -> None:
    assert answer.status_code == 200, answer.status_code  # the login page again
    assert f'data-problem="{problem.code}"' in answer.text, answer.text
    assert str(problem.words) in answer.text


def last_denial() -> AccessDenial:
    return AccessDenial.objects.order_by("-id").first()


@pytest.mark.django_db
def test_an_operator_signs_in_over_starttls_and_gets_the_role_of_their_group(directory):
    directory.add_user("dora", PASSWORD, groups=["lifecycle-operators"], mail="dora@plant.example",
                       given_name="Dora", surname="Schmidt")
    with directory_settings(directory):
        client, answer = log_in("dora")
        assert answer.status_code == 302 and answer["Location"] == "/", answer
        assert client.get("/").status_code == 200
    user = get_user_model().objects.get(username="dora")
    assert (user.email, user.first_name, user.last_name) == ("dora@plant.example", "Dora", "Schmidt")
    assert not user.has_usable_password()  # the directory checks it, never this site
    assert list(user.groups.values_list("name", flat=True)) == ["operator"]
    account = user.directory_account
    assert (account.source, account.role) == (DirectoryAccount.LDAP, "operator")
    assert "lifecycle-operators" in account.groups


@pytest.mark.django_db
def test_the_role_follows_the_directory_at_every_sign_in(directory):
    dn = directory.add_user("ines", PASSWORD, groups=["plant-it", "plant-staff"])
    with directory_settings(directory, url=directory.tls_url):  # LDAPS, certificate checked
        assert log_in("ines")[1].status_code == 302
        user = get_user_model().objects.get(username="ines")
        assert list(user.groups.values_list("name", flat=True)) == ["admin"] and user.is_staff  # the highest

        directory.leave_group(dn, "plant-it")
        assert log_in("ines")[1].status_code == 302
        user.refresh_from_db()
        assert list(user.groups.values_list("name", flat=True)) == ["viewer"] and not user.is_staff

        directory.leave_group(dn, "plant-staff")
        _client, answer = log_in("ines")
        refused_with(answer, problems.NO_ROLE)
    denial = last_denial()
    assert (denial.code, denial.username, denial.detail) == ("login_failed", "ines", problems.NO_ROLE.summary)


@pytest.mark.django_db
def test_a_directory_session_ends_after_its_hours_and_the_next_sign_in_reads_the_groups(directory):
    """A group taken away in the directory cannot be seen until the next sign-in: that comes after
    LIFECYCLE_DIRECTORY_SESSION_HOURS however busy the session. Local accounts keep Django's."""
    dn = directory.add_user("sven", PASSWORD, groups=["lifecycle-operators"])
    with directory_settings(directory), override_settings(LIFECYCLE_DIRECTORY_SESSION_HOURS=2 / 3600):
        client, answer = log_in("sven")
        assert answer.status_code == 302 and client.get("/").status_code == 200
        assert 0 < client.session.get_expiry_age() <= 2
        directory.leave_group(dn, "lifecycle-operators")
        stack.wait_for(lambda: client.get("/").status_code == 302, 10, "the directory session to end")
        assert client.get("/")["Location"].startswith("/login/")
        refused_with(log_in("sven")[1], problems.NO_ROLE)

        make_user("lena-local", "operator")
        local, answer = log_in("lena-local", "a-test-password-123")
        assert answer.status_code == 302
        assert local.session.get_expiry_age() == settings.SESSION_COOKIE_AGE  # two weeks


@pytest.mark.django_db
def test_a_group_within_a_mapped_group_gives_its_role(directory):
    """Active Directory's usual nesting (AGDLP): the user is in a shift's group, that one in the
    group the site maps; groups that list each other end the search, and are each read once."""
    dn = directory.add_user("nina", PASSWORD, groups=["shift-b"])
    shift = directory.join_group(directory.join_group(directory.join_group(
        f"cn=shift-b,{directory.groups}", "hall-3-team"), "hall-3"), "lifecycle-operators")
    directory.join_group(shift, "hall-3-team")  # a loop: lifecycle-operators in hall-3-team
    directory.add_user("oskar", PASSWORD, groups=["shift-c"])
    with directory_settings(directory):
        assert log_in("nina")[1].status_code == 302
        account = DirectoryAccount.objects.get(subject="nina")
        assert account.role == "operator"
        assert {"shift-b", "hall-3-team", "hall-3", "lifecycle-operators"} <= set(account.groups.split(", "))
        refused_with(log_in("oskar")[1], problems.NO_ROLE)  # a group in no mapped group
        directory.leave_group(dn, "shift-b")
        refused_with(log_in("nina")[1], problems.NO_ROLE)


@pytest.mark.django_db
def test_no_mapped_group_no_account(directory):
    directory.add_user("visitor", PASSWORD, groups=["visitors"])
    with directory_settings(directory):
        refused_with(log_in("visitor")[1], problems.NO_ROLE)
    assert not get_user_model().objects.filter(username="visitor").exists()  # taken back with the refusal


@pytest.mark.django_db
def test_a_local_account_is_never_taken_over_by_the_directory(directory):
    local = make_user("lena", "viewer")  # local password: a-test-password-123
    directory.add_user("lena", PASSWORD, groups=["plant-it"])
    with directory_settings(directory):
        _client, answer = log_in("lena")  # the local account's name: its own password only
        assert answer.status_code == 200 and "did not match" in answer.text
        # The directory matches names without regard to case and answers "lena": refused before any write.
        refused_with(log_in("LENA")[1], problems.LOCAL_NAME)
        assert log_in("lena", "a-test-password-123")[1].status_code == 302
    local.refresh_from_db()
    assert list(local.groups.values_list("name", flat=True)) == ["viewer"] and not local.is_staff
    assert not DirectoryAccount.objects.filter(user=local).exists()
    assert local.has_usable_password()


@pytest.mark.django_db
def test_a_wrong_password_is_on_record_and_throttled(directory, settings):
    directory.add_user("wanda", PASSWORD, groups=["plant-staff"])
    with directory_settings(directory):
        for _ in range(settings.AXES_FAILURE_LIMIT - 1):
            _client, answer = log_in("wanda", "not her password")
            assert answer.status_code == 200 and "did not match" in answer.text
            assert last_denial().detail == "wrong user name or password"
        assert log_in("wanda", "not her password")[1].status_code == 429  # the last one allowed
        _client, answer = log_in("wanda")  # the right one, too late
        assert answer.status_code == 429 and "Login blocked" in answer.text
    assert not get_user_model().objects.filter(username="wanda").exists()


@pytest.mark.django_db
def test_a_directory_that_is_down_or_frozen_is_a_bounded_refusal_in_words(directory):
    directory.add_user("otto", PASSWORD, groups=["lifecycle-operators"])
    make_user("local-admin", "admin")
    with directory_settings(directory):
        directory.stop()
        try:
            started = time.monotonic()
            refused_with(log_in("otto")[1], problems.DIRECTORY_UNREACHABLE)
            assert time.monotonic() - started < 2 * TIMEOUT_S + 2
            assert last_denial().detail == problems.DIRECTORY_UNREACHABLE.summary
            assert log_in("local-admin", "a-test-password-123")[1].status_code == 302  # local accounts still work
        finally:
            directory.start()
        assert log_in("otto")[1].status_code == 302

        with stack.frozen(directory.pid):  # accepts connections, answers nothing
            started = time.monotonic()
            refused_with(log_in("otto")[1], problems.DIRECTORY_UNREACHABLE)
            waited = time.monotonic() - started
        assert waited < 3 * TIMEOUT_S + 3, waited
        assert log_in("otto")[1].status_code == 302


@pytest.mark.django_db
def test_a_directory_certificate_not_signed_by_the_given_ca_is_refused(directory):
    directory.add_user("theo", PASSWORD, groups=["plant-staff"])
    system_cas = "/etc/ssl/certs/ca-certificates.crt"  # trusted CAs, none of which signed the test directory
    for url in (directory.url, directory.tls_url):
        with directory_settings(directory, url=url, ca_file=system_cas):
            refused_with(log_in("theo")[1], problems.DIRECTORY_UNREACHABLE)
    assert not get_user_model().objects.filter(username="theo").exists()


@pytest.mark.django_db
def test_a_service_account_set_as_a_dn_or_by_its_name_does_the_lookups(directory):
    """LIFECYCLE_LDAP_BIND_USER as the Edge form describes it (a DN), or as a name under the user
    base: the library rebinds as it after the user's own bind. A DN used to be formed like a
    user's name (uid=cn\\3D...), its bind failed, and every sign-in with it."""
    lookup_dn = directory.add_user("lookup", "lookup-secret")
    directory.add_user("emil", PASSWORD, groups=["lifecycle-operators"])
    for service in (lookup_dn, "lookup"):
        with directory_settings(directory, LIFECYCLE_LDAP_BIND_USER=service,
                                LIFECYCLE_LDAP_BIND_PASSWORD="lookup-secret"):
            client, answer = log_in("emil")
            assert answer.status_code == 302 and answer["Location"] == "/", (service, answer)
    assert list(get_user_model().objects.get(username="emil").groups.values_list("name", flat=True)) == ["operator"]


@pytest.mark.django_db
def test_a_token_follows_the_directory_which_the_service_account_asks_now_and_then(directory):
    """A token works without a sign-in; with a service account the site asks the directory about
    its account when it is used (at most every 15 minutes): the role follows the groups, and an
    account the directory no longer has loses its role, its token refused saying why, until it
    signs in again."""
    from datetime import timedelta

    from django.utils import timezone

    from lifecycle_site.api import grants
    from lifecycle_site.api.models import ApiToken
    from lifecycle_site.sign_in import directory_check

    lookup = directory.add_user("lookup-tokens", "lookup-secret")
    dn = directory.add_user("tara", PASSWORD, groups=["lifecycle-operators"])
    service = {"LIFECYCLE_LDAP_BIND_USER": lookup, "LIFECYCLE_LDAP_BIND_PASSWORD": "lookup-secret"}

    def used():
        return Client().get("/api/v1/robots", HTTP_AUTHORIZATION=f"Bearer {token}")

    def roles() -> list[str]:
        return list(get_user_model().objects.get(username="tara").groups.values_list("name", flat=True))

    def a_while_later() -> None:  # the last word of the directory is older than 15 minutes
        DirectoryAccount.objects.filter(user__username="tara").update(
            last_sign_in=timezone.now() - timedelta(minutes=20), confirmed=None)
        directory_check.forget()
        grants.forget()

    with directory_settings(directory, **service):
        assert log_in("tara")[1].status_code == 302
        _, token = ApiToken.issue(get_user_model().objects.get(username="tara"), "line PC")
        assert used().status_code == 200 and roles() == ["operator"]

        directory.leave_group(dn, "lifecycle-operators")
        directory.join_group(dn, "plant-it")
        a_while_later()
        assert used().status_code == 200 and roles() == ["admin"]  # the role the directory gives now
        assert DirectoryAccount.objects.get(user__username="tara").confirmed is not None

        directory.leave_group(dn, "plant-it")
        a_while_later()
        answer = used()
        assert answer.status_code == 403 and roles() == []  # no mapped group: no role, nothing allowed

    with directory_settings(directory, url=f"ldap://127.0.0.1:{stack.free_port()}", **service):
        directory.join_group(dn, "lifecycle-operators")  # back in the group, but the site cannot ask
        a_while_later()
        started = time.monotonic()
        assert used().status_code == 403 and roles() == []  # nothing changes until it can
        assert time.monotonic() - started < 2 * TIMEOUT_S + 2

    with directory_settings(directory, **service):
        directory.delete(dn)
        a_while_later()
        for _ in range(2):  # the lookup, then the account as it left it: refused alike, not as a guessed token
            answer = used()
            assert answer.status_code == 401 and answer.json()["error"]["code"] == "directory_refused", \
                answer.content
            assert "tara, a company account that the company directory no longer has" in \
                answer.json()["error"]["message"]
            assert last_denial().code == "directory_refused"
        assert roles() == [] and DirectoryAccount.objects.get(user__username="tara").role == ""

        directory.add_user("tara", PASSWORD)  # back (a mistake mended); the group still names her DN
        assert log_in("tara")[1].status_code == 302
        assert used().status_code == 200 and roles() == ["operator"]
