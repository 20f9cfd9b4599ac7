"""German beside English: nothing a template shows is left unmarked, every marked string has a
German text, the compiled catalogues are the committed ones, and each way of choosing the
language works (the browser's Accept-Language, the header's choice kept per user, the API's
messages with unchanged codes, the script catalogue)."""
from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from django.test import Client

from tests import translations
from tests.conftest import client_of, make_user

CATALOGUES = translations.LOCALE / "de" / "LC_MESSAGES"


def test_every_template_text_is_marked_for_translation():
    unmarked = {str(path.relative_to(translations.ROOT)): texts
                for path in translations.all_templates() if (texts := translations.unmarked(path))}
    assert not unmarked, "text not marked for translation (docs/translation.md):\n" + "\n".join(
        f"{path}: {text}" for path, texts in unmarked.items() for text in texts)


@pytest.mark.parametrize("domain", ["django", "djangojs"])
def test_every_marked_string_has_a_german_text(domain):
    missing = translations.missing(domain)
    assert not missing, f"{len(missing)} marked strings without German text ({domain}.po; make translations):\n" \
        + "\n".join(missing)


@pytest.mark.parametrize("domain", ["django", "djangojs"])
def test_the_compiled_catalogues_are_the_committed_texts(domain, tmp_path):
    compiled = tmp_path / f"{domain}.mo"
    subprocess.run(["msgfmt", "--check", "-o", str(compiled), str(CATALOGUES / f"{domain}.po")], check=True)
    assert compiled.read_bytes() == (CATALOGUES / f"{domain}.mo").read_bytes(), \
        f"{domain}.mo is older than {domain}.po: run make translations"


def test_the_catalogue_parts_were_merged():
    """Parts (locale/de/parts/) are a translator's hand-over; merged, they are gone."""
    assert not list((translations.LOCALE / "de" / "parts").glob("*.po"))


@pytest.mark.django_db
def test_a_german_browser_gets_german_pages_and_the_header_choice_follows_the_user():
    page = Client(HTTP_ACCEPT_LANGUAGE="de-DE,de;q=0.9,en;q=0.5").get("/login/")
    assert '<html lang="de">' in page.text and "Benutzername" in page.text and "Passwort" in page.text
    assert page["Content-Language"] == "de"
    assert '<html lang="en">' in Client(HTTP_ACCEPT_LANGUAGE="en-GB").get("/login/").text

    make_user("greta-operator", "operator")
    browser = Client(HTTP_ACCEPT_LANGUAGE="de")
    assert browser.post("/login/", {"username": "greta-operator", "password": "a-test-password-123"}).status_code == 302
    assert "Flotte" in browser.get("/").text
    chosen = browser.post("/language/", {"language": "en", "next": "/audit/"})
    assert chosen.status_code == 302 and chosen["Location"] == "/audit/"
    assert "Audit history" in browser.get("/").text  # her choice beats her browser's language

    elsewhere = Client(HTTP_ACCEPT_LANGUAGE="de")  # another browser, German too: her choice follows her
    elsewhere.post("/login/", {"username": "greta-operator", "password": "a-test-password-123"})
    assert '<html lang="en">' in elsewhere.get("/").text


@pytest.mark.django_db
def test_a_language_choice_is_checked_and_the_way_back_stays_on_the_site():
    client = Client()
    assert client.post("/language/", {"language": "fr"}).status_code == 400
    assert client.get("/language/").status_code == 405
    answer = client.post("/language/", {"language": "de", "next": "https://evil.example/"})
    assert answer.status_code == 302 and answer["Location"] == "/"
    assert answer.cookies["django_language"].value == "de"
    assert '<html lang="de">' in client.get("/login/").text  # the cookie: the login page after a logout


@pytest.mark.django_db
def test_the_script_catalogue_is_german_for_a_german_page():
    catalogue = Client(HTTP_ACCEPT_LANGUAGE="de").get("/jsi18n/")
    assert catalogue.status_code == 200 and "Handlungsbedarf" in catalogue.content.decode()
    assert "Handlungsbedarf" not in Client(HTTP_ACCEPT_LANGUAGE="en").get("/jsi18n/").content.decode()


def test_the_catalogues_are_utf8_and_german():
    for domain in ("django", "djangojs"):
        header = Path(CATALOGUES / f"{domain}.po").read_text().split("\n\n", 1)[0]
        assert "charset=UTF-8" in header and "Language: de" in header and "nplurals=2" in header


@pytest.mark.django_db
def test_the_api_keeps_its_codes_and_answers_in_the_askers_language():
    make_user("ines-operator", "operator")
    client = client_of("ines-operator", "operator")
    german = client.get("/api/v1/nodes/no-robot.no-node", HTTP_ACCEPT_LANGUAGE="de")
    english = client.get("/api/v1/nodes/no-robot.no-node", HTTP_ACCEPT_LANGUAGE="en")
    assert german.status_code == english.status_code == 404
    assert german.json()["error"]["code"] == english.json()["error"]["code"] == "not_found"
    assert german.json()["error"]["message"].startswith("Es gibt keinen Knoten mit der ID")
    assert english.json()["error"]["message"].startswith("There is no node with id")


@pytest.mark.django_db
@pytest.mark.parametrize(("environment", "words"), [
    ({"LIFECYCLE_LANGUAGE": "de"}, "Es gibt keinen Knoten"),
    ({"LANG": "de_DE.UTF-8"}, "Es gibt keinen Knoten"),
    ({"LC_ALL": "C.UTF-8", "LANG": "de_DE.UTF-8"}, "There is no node"),  # LC_ALL wins, as for gettext
    ({"LANG": "fr_FR.UTF-8"}, "There is no node"),
])
def test_the_cli_speaks_the_shells_language(environment, words, monkeypatch):
    import io

    from django.core.management import CommandError, call_command

    for name in ("LIFECYCLE_LANGUAGE", "LC_ALL", "LC_MESSAGES", "LANG"):
        monkeypatch.delenv(name, raising=False)
    for name, value in environment.items():
        monkeypatch.setenv(name, value)
    stderr = io.StringIO()
    with pytest.raises(CommandError):
        call_command("lifecycle", "get", "no-robot.no-node", stdout=io.StringIO(), stderr=stderr)
    assert words in stderr.getvalue(), stderr.getvalue()


def test_operation_words_are_translated_where_the_site_shows_them():
    from django.utils import translation

    from lifecycle_site.operations import words
    from ros_gateway.shared import operations

    shutdown = operations.get("shutdown")
    with translation.override("de"):
        assert words.button(shutdown) == "Herunterfahren"
        assert words.question(shutdown, "agv-1") == "{nodes} von agv-1 herunterfahren?"
    assert words.question(shutdown, "agv-1") == "Shut down {nodes} of agv-1?"
    assert shutdown.button == "Shut down"  # the shared table itself stays English (the gateway has no Django)


def test_alert_mails_and_summaries_are_in_the_sites_language(settings):
    from django.utils import timezone, translation

    from lifecycle_site.alerts import conditions, engine
    from lifecycle_site.alerts.models import Alert

    now = timezone.now()
    alert = Alert(rule_name="lidar down", subject="agv-1./lidar", summary="…", since=now, fired_at=now,
                  resolved_at=now)
    settings.LANGUAGE_CODE = "de"
    subject, body = engine.email_text(alert, "resolved")
    assert subject == "[BEHOBEN] lidar down: agv-1./lidar"
    assert "Regel: lidar down" in body and "Behoben: " in body
    with translation.override(settings.LANGUAGE_CODE):  # as Engine.evaluate writes a summary
        gone = conditions._gone_text("/lidar", "agv-1", "unreachable")
    assert gone.startswith("Knoten /lidar auf Roboter agv-1 antwortet nicht mehr")
    settings.LANGUAGE_CODE = "en"
    assert engine.email_text(alert, "resolved")[0] == "[RESOLVED] lidar down: agv-1./lidar"


def test_a_live_socket_takes_its_pages_language():
    from lifecycle_site.languages.choice import of_scope

    def scope(session=None, **headers):
        return {"session": session, "headers": [(k.replace("_", "-").encode(), v.encode()) for k, v in headers.items()]}

    assert of_scope(scope(accept_language="fr-FR,de;q=0.8,en;q=0.5")) == "de"  # the first one the site has
    assert of_scope(scope(accept_language="*")) == "en"
    assert of_scope(scope(cookie="django_language=de; csrftoken=x", accept_language="en")) == "de"
    assert of_scope(scope(cookie='bad"cookie=; django_language', accept_language="de")) == "de"
    assert of_scope(scope({"language": "en"}, cookie="django_language=de", accept_language="de")) == "en"
