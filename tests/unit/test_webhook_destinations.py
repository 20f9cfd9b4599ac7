"""Where alert webhooks may go: not to this machine, link-local (cloud metadata) or other
internal addresses unless LIFECYCLE_WEBHOOK_ALLOW lists them; checked when a receiver is saved
and again, on the resolved addresses, at every delivery; no credentials in URLs or logs.

Real parts: the admin through Django's test client, real HTTP(S) receivers on 127.0.0.1, the
real delivery threads and log. Names other than localhost are answered by a stand-in resolver
(``dns``): the test cannot change the machine's DNS."""
from __future__ import annotations

import datetime
import importlib
import ipaddress
import logging
import socket
import ssl
import subprocess
import sys
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID
from django.utils import timezone

from lifecycle_site.alerts.delivery import Job, post_webhook
from lifecycle_site.alerts.destinations import Allow, parse_allow
from lifecycle_site.alerts.engine import Evaluator
from lifecycle_site.alerts.models import Delivery, Receiver, Rule
from lifecycle_site.fleet.models import Gateway, ManagedNode, Robot
from lifecycle_site.settings import _webhook_allow
from tests import stack
from tests.unit.test_alerts_api import client_of
from tests.unit.test_alerts_delivery import WebhookReceiver, drain

PASSWORD = "hunter2-not-for-logs"


@pytest.fixture
def allow(settings):
    """Set LIFECYCLE_WEBHOOK_ALLOW as the process would read it (empty: the default)."""
    def set_to(text: str) -> None:
        settings.LIFECYCLE_WEBHOOK_ALLOW = parse_allow(text)
    set_to("")
    return set_to


@pytest.fixture
def dns(monkeypatch):
    """Answers for names of the tests' own (a dict: name -> addresses, or a function giving
    them at each lookup); other names and addresses as the machine resolves them."""
    answers: dict = {}
    real = socket.getaddrinfo

    def getaddrinfo(host, port, *args, **kwargs):
        if host not in answers:
            return real(host, port, *args, **kwargs)
        addresses = answers[host]() if callable(answers[host]) else answers[host]
        return [info for address in addresses for info in real(address, port, *args, **kwargs)]

    monkeypatch.setattr(socket, "getaddrinfo", getaddrinfo)
    return answers


@pytest.fixture
def finalized_node(db) -> ManagedNode:
    robot = Robot.objects.create(name="wd-agv", domain_id=66, gateway=Gateway.objects.create(name="wd-cell"))
    now = timezone.now()
    return ManagedNode.objects.create(robot=robot, name="/planner", alive=True, state_label="finalized", state_id=4,
                                      first_seen=now, last_seen=now, state_changed=now)


@pytest.fixture
def fast_retries(settings):
    settings.ALERTS = {**settings.ALERTS, "RETRY_BASE_S": 0.2, "RETRY_CAP_S": 1.0, "ATTEMPTS": 3, "TIMEOUT_S": 2.0}


@pytest.fixture
def admin_client(db):
    return client_of("ada-admin", "admin")


def own_address() -> str:
    """This machine's address towards the world (no packet is sent)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.connect(("198.51.100.1", 9))
        return probe.getsockname()[0]


def save(client, url: str, name: str = "hook") -> str:
    """Add a webhook receiver in the admin: '' when saved, else the page (with its error)."""
    response = client.post("/admin/alerts/receiver/add/", {"name": name, "kind": "webhook", "url": url,
                                                           "secret": "", "emails": "", "enabled": "on"})
    return "" if response.status_code == 302 else response.content.decode()


@pytest.mark.parametrize(("url", "why"), [
    ("http://127.0.0.1:8000/api/v1/robots", "127.0.0.1 is a loopback address (this machine)"),
    ("http://localhost:6479/", "localhost resolves to 127.0.0.1, which is a loopback address"),
    ("http://[::ffff:127.0.0.1]/", "is a loopback address"),
    ("http://169.254.169.254/latest/meta-data/", "a link-local address, where cloud metadata services answer"),
    ("http://0.0.0.0:8000/", "an unspecified address"),
    ("http://10.20.0.5/tickets", "10.20.0.5 is an internal address; allowed only if LIFECYCLE_WEBHOOK_ALLOW lists "
                                 "it or its network"),
    ("http://[fd12::5]/", "an internal address"),
], ids=["loopback", "localhost", "mapped", "metadata", "unspecified", "private", "ula"])
def test_webhooks_to_this_machine_metadata_or_internal_hosts_are_refused_when_saved(admin_client, allow, url, why):
    page = save(admin_client, url)
    assert why in page, "saved" if not page else page[:200]
    assert not Receiver.objects.exists()


def test_internal_receivers_listed_by_an_administrator_are_accepted(admin_client, allow, dns):
    dns.update({"tickets.plant": ["10.30.0.7"], "two-faced.plant": ["10.30.0.8", "169.254.169.254"]})
    allow("10.20.0.0/16,tickets.plant,two-faced.plant")
    assert save(admin_client, "http://10.20.0.5/tickets", "by network") == ""
    assert save(admin_client, "https://tickets.plant/api/hook", "by name") == ""
    assert save(admin_client, "http://93.184.215.14/hook", "public") == ""
    assert save(admin_client, "https://not-yet-in-dns.plant.invalid/hook", "unresolved") == ""  # checked when sent
    assert "10.21.0.5 is an internal address" in save(admin_client, "http://10.21.0.5/", "outside")
    # every address a name resolves to is checked
    assert "two-faced.plant resolves to 169.254.169.254, which is a link-local" in save(
        admin_client, "http://two-faced.plant/", "metadata too")
    allow("0.0.0.0/0")  # wide open, still not: metadata, nor this machine through a network
    assert "link-local" in save(admin_client, "http://169.254.169.254/", "metadata")
    assert "is a loopback address" in save(admin_client, "http://127.0.0.1:8000/", "loopback")
    mine = own_address()
    network = ipaddress.ip_network(f"{mine}/24", strict=False)
    allow(str(network))
    assert f"{mine} is an address of this machine; allowed only if LIFECYCLE_WEBHOOK_ALLOW lists {mine} itself" in (
        save(admin_client, f"http://{mine}:8000/", "own"))
    allow(mine)
    assert save(admin_client, f"http://{mine}:8000/", "own") == ""
    assert sorted(Receiver.objects.values_list("name", flat=True)) == [
        "by name", "by network", "own", "public", "unresolved"]


def test_a_delivery_checks_the_address_again_and_sends_nothing_there(finalized_node, fast_retries, allow, caplog):
    """A receiver saved before the check existed (or whose name now resolves elsewhere)."""
    receiver = WebhookReceiver()
    caplog.set_level(logging.WARNING)
    rule = Rule.objects.create(name="finalized", kind=Rule.Kind.STATE, state="finalized")
    rule.receivers.add(Receiver.objects.create(name="internal", url=receiver.url))
    evaluator = Evaluator()
    try:
        evaluator.evaluate()
        drain(evaluator, lambda: Delivery.objects.filter(outcome__in=("delivered", "failed")).exists())
    finally:
        evaluator.dispatcher.stop()
        receiver.close()
    assert receiver.requests == []
    failed = Delivery.objects.get()  # one attempt: a refusal is not retried
    assert (failed.outcome, failed.attempt) == ("failed", 1)
    assert failed.error == (f"not sent to {receiver.url}: 127.0.0.1 is a loopback address (this machine); "
                            "allowed only if LIFECYCLE_WEBHOOK_ALLOW lists 127.0.0.1 itself")


def job_for(url: str) -> Job:
    return Job(1, "hook", "webhook", 1, "firing", "d1", body=b"{}", url=url)


def test_a_name_is_resolved_once_per_delivery_and_the_checked_address_is_used(allow, dns):
    allow("127.0.0.1")
    receiver = WebhookReceiver()
    port = receiver.server.server_address[1]
    answers = iter([["127.0.0.1"]])
    # after the first lookup the name points elsewhere: an address that was never checked
    dns["hooks.plant.test"] = lambda: next(answers, ["127.0.0.2"])
    try:
        code, error, _ = post_webhook(job_for(f"http://hooks.plant.test:{port}/hook"), 2.0)
    finally:
        receiver.close()
    assert (code, error) == (200, "")
    assert receiver.requests[0]["headers"]["Host"] == f"hooks.plant.test:{port}"


def test_redirects_are_not_followed(allow):
    allow("127.0.0.1")
    receiver = WebhookReceiver(answers=(302,))
    try:
        code, error, retry = post_webhook(job_for(receiver.url), 2.0)
    finally:
        receiver.close()
    assert (code, retry, len(receiver.requests)) == (302, False, 1)
    assert error == "the receiver answered HTTP 302 Found"


def test_through_a_proxy_the_url_is_checked_and_the_proxy_connects(allow, monkeypatch):
    proxy = WebhookReceiver()  # stands in for the plant's HTTP proxy: it is asked for the absolute URL
    for name in ("no_proxy", "NO_PROXY", "all_proxy", "ALL_PROXY"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("http_proxy", f"http://127.0.0.1:{proxy.server.server_address[1]}")
    try:
        sent = post_webhook(job_for("http://hooks.example.invalid/alerts"), 2.0)  # a name only the proxy knows
        metadata = post_webhook(job_for("http://169.254.169.254/latest/meta-data/"), 2.0)
    finally:
        proxy.close()
    assert sent == (200, "", False)
    assert [r["path"] for r in proxy.requests] == ["http://hooks.example.invalid/alerts"]
    assert metadata == (None, "not sent to http://169.254.169.254/latest/meta-data/: 169.254.169.254 is a link-local "
                              "address, where cloud metadata services answer; webhooks never go there", False)


def certificate_for(name: str, directory: Path) -> tuple[Path, Path]:
    """A CA (its certificate file: the client's trust) and a server certificate for ``name``
    only (no address in it), signed by it: (CA file, server certificate and key file)."""
    now = datetime.datetime.now(datetime.timezone.utc)

    def issue(subject: str, key, issuer: str, issuer_key, ca: bool, san: str | None) -> x509.Certificate:
        builder = (x509.CertificateBuilder().subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, subject)]))
                   .issuer_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, issuer)]))
                   .public_key(key.public_key()).serial_number(x509.random_serial_number())
                   .not_valid_before(now - datetime.timedelta(minutes=5))
                   .not_valid_after(now + datetime.timedelta(days=1))
                   .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True))
        if san:
            builder = builder.add_extension(x509.SubjectAlternativeName([x509.DNSName(san)]), critical=False)
        if ca:
            builder = builder.add_extension(x509.KeyUsage(False, False, False, False, False, True, True, False, False),
                                            critical=True)
        return builder.sign(issuer_key, hashes.SHA256())

    ca_key, key = ec.generate_private_key(ec.SECP256R1()), ec.generate_private_key(ec.SECP256R1())
    ca = issue("test CA", ca_key, "test CA", ca_key, True, None)
    server = issue(name, key, "test CA", ca_key, False, name)
    ca_file, server_file = directory / "ca.pem", directory / "server.pem"
    ca_file.write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    server_file.write_bytes(server.public_bytes(serialization.Encoding.PEM) + key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()))
    return ca_file, server_file


def test_https_keeps_the_host_name_for_the_server_name_and_certificate(allow, dns, tmp_path, monkeypatch):
    allow("127.0.0.1")
    dns["hooks.plant.test"] = ["127.0.0.1"]
    ca_file, server_file = certificate_for("hooks.plant.test", tmp_path)
    monkeypatch.setenv("SSL_CERT_FILE", str(ca_file))  # the client's trust: this CA only
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.load_cert_chain(server_file)
    seen: dict[str, list] = {"server names": [], "hosts": []}

    def server_name(sock: ssl.SSLSocket, name: str | None, ctx: ssl.SSLContext) -> None:
        seen["server names"].append(name)

    context.sni_callback = server_name

    class Handler(BaseHTTPRequestHandler):
        def do_POST(self) -> None:  # noqa: N802 - http.server's name
            self.rfile.read(int(self.headers.get("Content-Length", 0)))
            seen["hosts"].append(self.headers["Host"])
            self.send_response(204)
            self.end_headers()

        def log_message(self, *args) -> None:
            pass

    class TLSServer(ThreadingHTTPServer):
        def get_request(self):
            sock, address = self.socket.accept()
            return context.wrap_socket(sock, server_side=True), address

    server = TLSServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    port = server.server_address[1]
    try:
        code, error, _ = post_webhook(job_for(f"https://hooks.plant.test:{port}/hook"), 3.0)
        # the same server by its address: the certificate does not name it, so nothing is sent
        by_address = post_webhook(job_for(f"https://127.0.0.1:{port}/hook"), 3.0)
    finally:
        server.shutdown()
        server.server_close()
    assert (code, error) == (204, "")
    # (no server name is sent for an address)
    assert seen == {"server names": ["hooks.plant.test", None], "hosts": [f"hooks.plant.test:{port}"]}
    assert by_address[0] is None and "certificate verify failed" in by_address[1]


def test_a_url_with_credentials_is_refused_and_its_password_is_never_logged(
        admin_client, finalized_node, fast_retries, allow, caplog):
    allow("127.0.0.1")
    caplog.set_level(logging.DEBUG)
    receiver = WebhookReceiver()
    url = receiver.url.replace("http://", f"http://ops:{PASSWORD}@")
    page = save(admin_client, url)
    assert "a user name or password in the URL is not accepted" in page
    assert "set the receiver&#x27;s secret and check X-Lifecycle-Signature" in page
    assert not Receiver.objects.exists()
    # one saved before the check: never sent, and the password appears in no log, page or message
    rule = Rule.objects.create(name="finalized", kind=Rule.Kind.STATE, state="finalized")
    stored = Receiver.objects.create(name="old-hook", url=url)
    rule.receivers.add(stored)
    evaluator = Evaluator()
    try:
        evaluator.evaluate()
        drain(evaluator, lambda: Delivery.objects.filter(outcome__in=("delivered", "failed")).exists())
    finally:
        evaluator.dispatcher.stop()
        receiver.close()
    assert receiver.requests == []
    error = Delivery.objects.get().error
    assert error.startswith(f"not sent to {receiver.url.replace('http://', 'http://***@')}: a user name or password")
    listing = admin_client.get("/admin/alerts/receiver/").content.decode()
    deliveries = admin_client.get("/admin/alerts/delivery/").content.decode()
    assert "***@127.0.0.1" in listing
    for text in (error, caplog.text, listing, deliveries):
        assert PASSWORD not in text


def test_passwords_already_in_the_delivery_log_are_redacted_by_the_migration(db):
    from django.apps import apps

    migration = importlib.import_module("lifecycle_site.alerts.migrations.0002_redact_delivery_errors")
    old = Delivery.objects.create(receiver_name="old", event="firing", outcome="retrying", at=timezone.now(),
                                  error=f"could not reach http://ops:{PASSWORD}@10.1.2.3:8080/hook: [Errno -2] "
                                        "Name or service not known; retry in 2 s")
    other = Delivery.objects.create(receiver_name="mail", event="firing", outcome="failed", at=timezone.now(),
                                    error="could not send e-mail: refused for shift@example.invalid")
    migration.redact_errors(apps, None)
    assert Delivery.objects.get(pk=old.pk).error == ("could not reach http://***@10.1.2.3:8080/hook: [Errno -2] "
                                                     "Name or service not known; retry in 2 s")
    assert Delivery.objects.get(pk=other.pk).error == other.error


@pytest.mark.parametrize(("value", "why"), [
    ("10.20.0.1/16", "'10.20.0.1/16' has host bits set; write the network, e.g. 10.20.0.0/16"),
    ("https://tickets.plant", "'https://tickets.plant' is not an address, a network (10.20.0.0/16) or a host name"),
    ("tickets.plant:8443", "is not an address, a network"),
    ("*", "is not an address, a network"),
    ("169.254.169.254", "'169.254.169.254' is a link-local address, where cloud metadata services answer: webhooks "
                        "never go there"),
])
def test_a_bad_allow_list_stops_the_process_naming_the_entry(monkeypatch, value, why):
    from django.core.exceptions import ImproperlyConfigured

    monkeypatch.setenv("LIFECYCLE_WEBHOOK_ALLOW", f"10.30.0.0/16, {value}")
    with pytest.raises(ImproperlyConfigured, match="LIFECYCLE_WEBHOOK_ALLOW: ") as refused:
        _webhook_allow()
    assert why in str(refused.value)
    monkeypatch.setenv("LIFECYCLE_WEBHOOK_ALLOW", " 10.30.0.0/16, Tickets.Plant., fd12::/64 ")
    assert _webhook_allow() == Allow((ipaddress.ip_network("10.30.0.0/16"), ipaddress.ip_network("fd12::/64")),
                                     frozenset({"tickets.plant"}))


def test_the_site_does_not_start_with_a_bad_allow_list():
    env = stack.environment(LIFECYCLE_WEBHOOK_ALLOW="10.20.0.1/16", DJANGO_SETTINGS_MODULE="lifecycle_site.settings")
    done = subprocess.run([sys.executable, "manage.py", "check"], env=env, capture_output=True, text=True,
                          timeout=60, cwd=Path(__file__).resolve().parents[2])
    assert done.returncode != 0
    assert "LIFECYCLE_WEBHOOK_ALLOW: '10.20.0.1/16' has host bits set" in done.stderr
