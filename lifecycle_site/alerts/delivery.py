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
import itertools
import logging
import threading
import time
import urllib.error
import urllib.request
from collections import deque
from dataclasses import dataclass, field
from datetime import datetime, timezone

from django.conf import settings
from django.core.mail import EmailMessage, get_connection

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
    url: str = ""
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


_opener = urllib.request.build_opener(_NoRedirects)


def post_webhook(job: Job, timeout: float) -> tuple[int | None, str, bool]:
    """POST the job's body: (status code, error text, worth retrying)."""
    headers = {"Content-Type": "application/json", "User-Agent": USER_AGENT,
               "X-Lifecycle-Event": job.event, "X-Lifecycle-Delivery": job.delivery_id}
    if job.secret:
        headers[SIGNATURE_HEADER] = sign(job.secret, job.body)
    request = urllib.request.Request(job.url, data=job.body, headers=headers, method="POST")
    try:
        with _opener.open(request, timeout=timeout) as response:
            response.read(MAX_RESPONSE_BYTES)
            return response.status, "", False
    except urllib.error.HTTPError as exc:
        code = exc.code
        retry = code >= 500 or code in (408, 429)
        return code, f"the receiver answered HTTP {code} {exc.reason}", retry
    except (urllib.error.URLError, OSError, ValueError) as exc:
        reason = getattr(exc, "reason", exc)
        return None, f"could not reach {job.url}: {reason}", True


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
