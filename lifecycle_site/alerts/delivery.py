"""Sending alert events to receivers, off the ingest loop: a bounded queue, worker threads,
retries with exponential backoff, and every wait bounded by a timeout.

The workers never touch the database: each attempt's result goes back to the ingest loop
(``Dispatcher.results``), which writes the delivery log. A webhook gets a JSON body signed
with HMAC-SHA256 (``X-Lifecycle-Signature: sha256=HEX`` over the exact body bytes).
"""
from __future__ import annotations

import hashlib
import heapq
import hmac
import http.client
import itertools
import logging
import socket
import ssl
import threading
import time
import urllib.error
import urllib.request
from collections import deque
from dataclasses import dataclass, field
from datetime import datetime, timezone

from django.conf import settings
from django.core.mail import EmailMessage, get_connection
from django.utils import translation

from lifecycle_site.alerts import destinations

log = logging.getLogger(__name__)

SIGNATURE_HEADER = "X-Lifecycle-Signature"
USER_AGENT = "lifecycle-manager-alerts/1"
MAX_RESPONSE_BYTES = 64 * 1024
RESULTS_KEPT = 10_000  # attempts not yet written to the log (the ingest loop drains them each second)


def sign(secret: str, body: bytes) -> str:
    """The signature header's value: ``sha256=`` and the hex HMAC-SHA256 of the body."""
    return "sha256=" + hmac.new(secret.encode(), body, hashlib.sha256).hexdigest()


def config() -> dict:
    return settings.ALERTS


@dataclass
class Job:
    """One event of one alert for one receiver; a snapshot, so workers need no database."""

    receiver_id: int
    receiver_name: str
    kind: str  # webhook | email
    alert_id: int
    event: str  # firing | resolved
    delivery_id: str
    body: bytes = b""  # webhook: the JSON body
    url: str = field(default="", repr=False)  # may hold a password (saved before they were refused)
    secret: str = field(default="", repr=False)
    emails: list[str] = field(default_factory=list)
    subject: str = ""  # e-mail
    text: str = ""
    attempt: int = 0


@dataclass
class Result:
    job: Job
    outcome: str  # delivered | retrying | failed
    at: datetime
    attempt: int  # the job's own count goes on with its retries
    status_code: int | None = None
    error: str = ""
    duration_ms: float | None = None


class _NoRedirects(urllib.request.HTTPRedirectHandler):
    def redirect_request(self, *args, **kwargs):  # a 3xx answer is reported as it is
        return None


class _PinnedHTTP(http.client.HTTPConnection):
    """Connects to the address that was checked; the Host header still names the URL's host."""

    def __init__(self, host: str, port: int, address: str, timeout: float) -> None:
        super().__init__(host, port, timeout=timeout)
        self.address = address

    def connect(self) -> None:
        self.sock = socket.create_connection((self.address, self.port), self.timeout)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


class _PinnedHTTPS(http.client.HTTPSConnection):
    """As _PinnedHTTP, with TLS: the server name sent and its certificate checked are the URL's host."""

    def __init__(self, host: str, port: int, address: str, timeout: float) -> None:
        super().__init__(host, port, timeout=timeout, context=ssl.create_default_context())
        self.address = address

    def connect(self) -> None:
        sock = socket.create_connection((self.address, self.port), self.timeout)
        self.sock = self._context.wrap_socket(sock, server_hostname=self.host)


def _post_direct(target: destinations.Target, body: bytes, headers: dict, timeout: float) -> tuple[int, str]:
    """POST to the first of the checked addresses that takes the connection: (status, reason)."""
    connection_class = _PinnedHTTPS if target.scheme == "https" else _PinnedHTTP
    failure: OSError | None = None
    for address in target.addresses:
        connection = connection_class(target.host, target.port, address, timeout)
        try:
            try:
                connection.connect()
            except OSError as exc:
                failure = exc
                continue
            connection.request("POST", target.path, body, headers)
            response = connection.getresponse()
            response.read(MAX_RESPONSE_BYTES)
            return response.status, response.reason
        finally:
            connection.close()
    raise failure or OSError("no address to connect to")


def _post_proxied(url: str, body: bytes, headers: dict, timeout: float) -> tuple[int, str]:
    request = urllib.request.Request(url, data=body, headers=headers, method="POST")
    opener = urllib.request.build_opener(_NoRedirects)  # its ProxyHandler reads HTTP(S)_PROXY now, as _proxied did
    try:
        with opener.open(request, timeout=timeout) as response:
            response.read(MAX_RESPONSE_BYTES)
            return response.status, response.reason
    except urllib.error.HTTPError as exc:
        return exc.code, str(exc.reason)


def _proxied(scheme: str, host: str) -> bool:
    """HTTP(S)_PROXY applies to this URL (NO_PROXY does not exempt it)."""
    return scheme in urllib.request.getproxies() and not urllib.request.proxy_bypass(host)


def post_webhook(job: Job, timeout: float) -> tuple[int | None, str, bool]:
    """POST the job's body to the checked address: (status code, error text, worth retrying).
    The URL in error texts is redacted (destinations.redact): no password reaches the log. The
    error text is stored in the delivery log: in English, whatever the site's language."""
    with translation.override("en"):
        return _post_webhook(job, timeout)


def _post_webhook(job: Job, timeout: float) -> tuple[int | None, str, bool]:
    shown = destinations.redact(job.url)
    headers = {"Content-Type": "application/json", "User-Agent": USER_AGENT,
               "X-Lifecycle-Event": job.event, "X-Lifecycle-Delivery": job.delivery_id}
    if job.secret:
        headers[SIGNATURE_HEADER] = sign(job.secret, job.body)
    try:
        parts, host, _ = destinations.split(job.url)
        if _proxied(parts.scheme, host):
            # The proxy connects, to what it resolves the name to; what this machine resolves it
            # to is checked all the same. A name only the proxy knows is the proxy's to judge.
            try:
                destinations.check(job.url)
            except OSError:
                pass
            code, reason = _post_proxied(job.url, job.body, headers, timeout)
        else:
            target = destinations.check(job.url)  # resolved now: the name may point elsewhere since it was saved
            code, reason = _post_direct(target, job.body, headers, timeout)
    except destinations.Refused as exc:
        return None, f"not sent to {shown}: {exc}", False
    except (urllib.error.URLError, OSError, ValueError, http.client.HTTPException) as exc:
        reason = exc.reason if isinstance(exc, urllib.error.URLError) else exc  # (an SSLError's reason is terse)
        return None, f"could not reach {shown}: {reason}", True
    if 200 <= code < 300:
        return code, "", False
    # 3xx included: redirects are not followed (the place they point to was not checked)
    return code, f"the receiver answered HTTP {code} {reason}", code >= 500 or code in (408, 429)


def send_email(job: Job, timeout: float) -> tuple[int | None, str, bool]:
    try:
        connection = get_connection(timeout=timeout)
        EmailMessage(job.subject, job.text, None, job.emails, connection=connection).send()
        return None, "", False
    except Exception as exc:  # noqa: BLE001 - SMTP, DNS, TLS ...: every failure is reported and retried
        return None, f"could not send e-mail: {type(exc).__name__}: {exc}", True


def backoff(attempt: int) -> float:
    """Seconds before attempt ``attempt + 1``: base, 2x base, 4x base ... up to the cap."""
    cfg = config()
    return min(cfg["RETRY_BASE_S"] * 2 ** (attempt - 1), cfg["RETRY_CAP_S"])


class Dispatcher:
    """A bounded queue of jobs (new ones and those waiting for their retry) and its workers."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._heap: list[tuple[float, int, Job]] = []  # (due, order, job)
        self._order = itertools.count()
        self._threads: list[threading.Thread] = []
        self._stopping = False
        self.results: deque[Result] = deque(maxlen=RESULTS_KEPT)
        self.dropped = 0

    def pending(self) -> int:
        with self._cond:
            return len(self._heap)

    def submit(self, job: Job) -> bool:
        """Queue a job; False (and counted) when the queue is full."""
        with self._cond:
            if len(self._heap) >= config()["QUEUE_SIZE"]:
                self.dropped += 1
                return False
            heapq.heappush(self._heap, (time.monotonic(), next(self._order), job))
            self._start()
            self._cond.notify()
        return True

    def _start(self) -> None:
        if self._threads:
            return
        for number in range(config()["WORKERS"]):
            thread = threading.Thread(target=self._work, name=f"alert-delivery-{number}", daemon=True)
            thread.start()
            self._threads.append(thread)

    def stop(self, timeout: float = 2.0) -> int:
        """Stop the workers (an attempt under way ends within its timeout); returns the jobs left."""
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
            left = len(self._heap)
        deadline = time.monotonic() + timeout
        for thread in self._threads:
            thread.join(max(deadline - time.monotonic(), 0.0))
        if left:
            log.warning("stopping with %d alert deliveries not sent (queued or waiting for a retry)", left)
        return left

    def _next(self) -> Job | None:
        with self._cond:
            while not self._stopping:
                now = time.monotonic()
                if self._heap and self._heap[0][0] <= now:
                    return heapq.heappop(self._heap)[2]
                wait = min(self._heap[0][0] - now, 1.0) if self._heap else 1.0
                self._cond.wait(wait)
        return None

    def _work(self) -> None:
        while (job := self._next()) is not None:
            self.results.append(self.attempt(job))

    def attempt(self, job: Job) -> Result:
        cfg = config()
        job.attempt += 1
        began = time.monotonic()
        send = post_webhook if job.kind == "webhook" else send_email
        code, error, retry = send(job, cfg["TIMEOUT_S"])
        took = round((time.monotonic() - began) * 1000, 1)
        at = datetime.now(timezone.utc)
        if not error:
            return Result(job, "delivered", at, job.attempt, code, "", took)
        if retry and job.attempt < cfg["ATTEMPTS"]:
            delay = backoff(job.attempt)
            with self._cond:
                heapq.heappush(self._heap, (time.monotonic() + delay, next(self._order), job))
                self._cond.notify()
            return Result(job, "retrying", at, job.attempt, code, f"{error}; retry in {delay:g} s", took)
        log.warning("alert %s (%s) to %s: gave up after %d attempts: %s", job.alert_id, job.event,
                    job.receiver_name, job.attempt, error)
        return Result(job, "failed", at, job.attempt, code, error, took)
