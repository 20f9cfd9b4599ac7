"""Whatever a client sends, the site answers with a 4xx at worst, never a 5xx, and the API answers
in its JSON error shape (docs/api.md, "Errors" and "Limits").

The real stack: Redis, the ingest process, the gateway, real rclpy lifecycle nodes, and the site
served as ``make demo`` and the image serve it (``python -m lifecycle_site.serve``: daphne), so
the HTTP layer's limits are covered too. First focused tests of those limits, then a seeded
fuzzer (LIFECYCLE_FUZZ_SEED, LIFECYCLE_FUZZ_REQUESTS) over every endpoint of the API and every
page and form of the dashboard; it checks the audit log against what reached the robot."""
from __future__ import annotations

import json
import os
import random
import socket
import time
from collections import Counter
from urllib.parse import urlparse

import pytest
from axes.models import AccessAttempt
from django.utils import timezone
from django.utils.crypto import get_random_string

from lifecycle_site.api import limits
from lifecycle_site.api.models import ApiToken
from lifecycle_site.audit.models import AccessDenial, ParameterRecord, TransitionRecord
from lifecycle_site.serve import HEADERS_LIMIT, LINE_LIMIT
from tests import stack
from tests.conftest import client_of, make_user
from tests.integration import fuzz_cases
from tests.integration.conftest import register, wait_node

ROBOT = fuzz_cases.ROBOT
SEED = int(os.environ.get("LIFECYCLE_FUZZ_SEED", "20261123"))
REQUESTS = int(os.environ.get("LIFECYCLE_FUZZ_REQUESTS", "1000"))


@pytest.fixture(scope="module")
def robot(gateway):
    started = timezone.now()
    register(ROBOT, stack.domain(11))
    process = stack.start_robot("fuzz-nodes", stack.domain(11), ",".join(fuzz_cases.NODES))
    for node in fuzz_cases.NODES:
        wait_node(None, f"{ROBOT}.{node}", alive=True, state="unconfigured", seen_since=started)
    yield process
    process.stop()


@pytest.fixture(scope="module")
def site(gateway):
    process, base = stack.start_site("fuzz-daphne")
    yield process, base
    process.stop()


@pytest.fixture(scope="module")
def who(live_db) -> fuzz_cases.Credentials:
    def session(username: str, role: str) -> str:
        client = client_of(username, role)
        return client.cookies["sessionid"].value

    return fuzz_cases.Credentials(
        operator_token=ApiToken.issue(make_user("fuzz-operator", "operator"), "fuzz")[1],
        viewer_token=ApiToken.issue(make_user("fuzz-viewer", "viewer"), "fuzz")[1],
        operator_session=session("fuzz-operator", "operator"),
        admin_session=session("fuzz-admin", "admin"),
        csrf=get_random_string(32),
    )


def exchange(base: str, raw: bytes, timeout: float = 60.0) -> tuple[int, dict[str, str], bytes]:
    """Send ``raw`` on a fresh connection; the status, headers and body of the answer (status 0:
    the connection ended without one)."""
    address = urlparse(base)
    with socket.create_connection((address.hostname, address.port), timeout=timeout) as conn:
        try:
            conn.sendall(raw)
        except (BrokenPipeError, ConnectionResetError):
            pass  # the server may answer and close before the whole request is sent: read on
        data = b""
        try:
            while chunk := conn.recv(65536):
                data += chunk
                head, _, body = data.partition(b"\r\n\r\n")
                length = next((int(line.split(b":", 1)[1]) for line in head.split(b"\r\n")
                               if line.lower().startswith(b"content-length:")), None)
                if length is not None and len(body) >= length:
                    break
        except ConnectionResetError:
            pass
    if not data.startswith(b"HTTP/1.1 "):
        return 0, {}, data
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = {k.strip().lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:])}
    return int(lines[0].split()[1]), headers, body


def request(method: str, target: str, headers: dict[str, str] | None = None, body: bytes = b"") -> bytes:
    lines = [f"{method} {target} HTTP/1.1", "Host: 127.0.0.1", "Connection: close"]
    lines += [f"{k}: {v}" for k, v in (headers or {}).items()]
    if body or method in ("POST", "PUT", "PATCH"):
        lines.append(f"Content-Length: {len(body)}")
    return ("\r\n".join(lines) + "\r\n\r\n").encode("latin-1") + body


def api_error(answer: tuple[int, dict[str, str], bytes], status: int, code: str) -> str:
    got, headers, body = answer
    assert got == status, answer
    assert headers["content-type"] == "application/json", answer
    error = json.loads(body)["error"]
    assert error["code"] == code and error["message"], error
    return error["message"]


# --- the HTTP layer's limits ---------------------------------------------------------------------
def test_a_request_line_over_the_limit_is_414_not_a_dropped_connection(site):
    _, base = site
    # Plain daphne closed the connection without any answer.
    long_id = "x" * (LINE_LIMIT + 100)
    message = api_error(exchange(base, request("GET", f"/api/v1/nodes/{long_id}")), 414, "uri_too_long")
    assert "longer than 16 KiB" in message
    api_error(exchange(base, request("GET", f"/api/v1/transitions?node={long_id}")), 414, "uri_too_long")
    status, headers, body = exchange(base, request("GET", f"/nodes/{long_id}/"))
    assert status == 414 and headers["content-type"].startswith("text/html") and b"longer than 16 KiB" in body


def test_ids_and_queries_just_under_the_limit_are_json_answers(site, who, robot):
    _, base = site
    auth = {"Authorization": f"Bearer {who.operator_token}"}
    room = LINE_LIMIT - len("GET /api/v1/transitions?node= HTTP/1.1")
    long_id = "x" * room
    message = api_error(exchange(base, request("GET", f"/api/v1/nodes/{long_id[:-10]}", auth)), 404, "not_found")
    assert len(message) < 300
    assert exchange(base, request("GET", f"/api/v1/transitions?node={long_id}", auth))[0] == 200
    api_error(exchange(base, request("GET", f"/api/v1/nodes?robot={long_id[:-5]}", auth)), 404, "not_found")
    fields = "&".join(["a=1"] * (room // 4))  # thousands of fields, under the line limit
    api_error(exchange(base, request("GET", f"/api/v1/transitions?{fields}", auth)), 400, "too_many_fields")
    api_error(exchange(base, request("POST", f"/api/v1/nodes/{long_id[:-30]}/transition", auth,
                                     b'{"transition": "configure"}')), 404, "not_found")
    session = {"Cookie": f"sessionid={who.operator_session}"}
    assert exchange(base, request("GET", f"/nodes/{long_id[:-10]}/", session))[0] == 404


def test_header_lines_over_the_limits_are_431(site):
    _, base = site
    # Plain daphne answered these with a bare "400 Bad Request" and no body.
    big = {"X-Big": "y" * (LINE_LIMIT + 10)}
    assert "header line" in api_error(exchange(base, request("GET", "/api/v1/robots", big)), 431, "headers_too_large")
    many = {f"X-H{i}": "z" * 100 for i in range(HEADERS_LIMIT // 100)}
    api_error(exchange(base, request("GET", "/api/v1/robots", many)), 431, "headers_too_large")
    count = {f"X-C{i}": "1" for i in range(600)}
    assert "500 header lines" in api_error(exchange(base, request("GET", "/api/v1/robots", count)), 431,
                                           "headers_too_large")


def test_a_body_over_the_limit_is_413_before_it_is_read(site, who):
    _, base = site
    auth = {"Authorization": f"Bearer {who.operator_token}", "Content-Type": "application/json"}
    big = b'{"transition": "configure", "pad": "' + b"x" * int(2.6 * 1024 * 1024) + b'"}'
    # Plain daphne and Django took 2.6 MB (Django's limit was 2.5 MB of form data, not of JSON).
    message = api_error(exchange(base, request("POST", f"/api/v1/nodes/{ROBOT}.joy_to_vel/transition", auth, big)),
                        413, "body_too_large")
    assert "larger than 1 MiB" in message
    assert json.loads(exchange(base, request("POST", "/api/v1/robots", auth, big))[2])["error"]["limit"] == 1048576
    status, headers, body = exchange(base, request("POST", "/login/", {"Content-Type": "text/plain"}, big))
    assert status == 413 and headers["content-type"].startswith("text/html") and b"1 MiB" in body
    # Announced, and not sent: refused at once, without waiting for it (Expect: 100-continue).
    announce = request("PATCH", "/api/v1/nodes/x/parameters", {**auth, "Expect": "100-continue",
                                                                 "Content-Length": str(10**9)})
    api_error(exchange(base, announce.replace(b"Content-Length: 0\r\n", b""), timeout=10), 413, "body_too_large")
    chunk = b"x" * 0x10000
    chunked = request("POST", "/api/v1/nodes/x/transition", {**auth, "Transfer-Encoding": "chunked"})
    chunked = chunked.replace(b"Content-Length: 0\r\n", b"") + b"10000\r\n" + chunk + b"\r\n"
    chunked += (b"10000\r\n" + chunk + b"\r\n") * 40 + b"0\r\n\r\n"
    api_error(exchange(base, chunked), 413, "body_too_large")
    at_limit = b"[" + b" " * (limits.body_limit() - 2) + b"]"  # just within: Django reads it
    api_error(exchange(base, request("POST", "/api/v1/nodes/x/transition", auth, at_limit)), 400, "missing_field")


def test_what_is_not_http_gets_a_400_with_a_reason(site):
    _, base = site
    status, headers, body = exchange(base, b"HELLO THERE\r\n\r\n")
    assert status == 400 and b"not valid HTTP/1.1" in body
    bad_length = request("POST", "/api/v1/robots", {"Content-Length": "abc"})
    api_error(exchange(base, bad_length.replace(b"Content-Length: 0\r\n", b"")), 400, "bad_request")


# --- found by the fuzzer, in files outside the API (the fix is described in the hardening report) ---
def import_file(base: str, who, content: bytes) -> tuple[int, dict[str, str], bytes]:
    boundary = "b0undary"
    body = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"p.yaml\"\r\n\r\n".encode()
            + content + f"\r\n--{boundary}--\r\n".encode())
    headers = {"Cookie": f"sessionid={who.operator_session}; csrftoken={who.csrf}", "X-CSRFToken": who.csrf,
               "Content-Type": f"multipart/form-data; boundary={boundary}"}
    return exchange(base, request("POST", f"/nodes/{ROBOT}.joy_to_vel/parameters/import", headers, body))


def test_a_deeply_nested_parameter_file_is_refused_not_a_500(site, who, robot):
    status, _, body = import_file(site[1], who, b"a: " + b"[" * 5000)
    assert status == 200 and b"lists or mappings nested more than 32 levels deep" in body


def test_a_parameter_file_of_nested_aliases_is_refused(site, who, robot):
    levels = "".join(f"    l{i}: &l{i} [" + ", ".join([f"*l{i - 1}"] * 10) + "]\n" for i in range(1, 6))
    bomb = f"/joy_to_vel:\n  ros__parameters:\n    l0: &l0 [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]\n{levels}".encode()
    status, _, body = import_file(site[1], who, bomb)
    assert status == 200 and len(body) < 200_000, len(body)
    assert b"aliases (*name) are not supported" in body


# --- the fuzzer -----------------------------------------------------------------------------------
def test_fuzzed_requests_get_no_5xx_and_are_audited_exactly(site, who, robot, gateway, ingest):
    process, base = site
    first_transition = TransitionRecord.objects.order_by("-id").values_list("id", flat=True).first() or 0
    first_parameter = ParameterRecord.objects.order_by("-id").values_list("id", flat=True).first() or 0
    first_denial = AccessDenial.objects.order_by("-id").values_list("id", flat=True).first() or 0
    fuzzer = fuzz_cases.Fuzzer(random.Random(SEED), who)
    failures: list[str] = []
    record_ids: set[int] = set()
    statuses: Counter[int] = Counter()
    parameter_results = transitions_reached = 0
    started = time.monotonic()
    try:
        for number in range(REQUESTS):
            case = fuzzer.draw()
            status, headers, body = exchange(base, case.raw())
            statuses[status] += 1
            problem = fuzz_cases.check(case, status, headers, body)
            if problem:
                failures.append(f"#{number} {case}: {problem}")
                continue
            outcome = fuzz_cases.reached(case, status, body)
            if outcome.transition_record is not None:
                transitions_reached += 1
                record_ids.add(outcome.transition_record)
            parameter_results += outcome.parameter_results
    finally:  # refusals on record from this address would count against later tests' logins and tokens
        AccessDenial.objects.filter(id__gt=first_denial).delete()
        AccessAttempt.objects.filter(username__startswith="fuzz-nobody-").delete()
    took = time.monotonic() - started
    assert not failures, f"seed {SEED}: {len(failures)} bad answers, e.g.\n" + "\n".join(failures[:15])
    # Still answering, and every part still running.
    auth = {"Authorization": f"Bearer {who.operator_token}"}
    status, _, body = exchange(base, request("GET", "/api/v1/robots", auth))
    assert status == 200 and ROBOT in {r["name"] for r in json.loads(body)["robots"]}
    assert process.alive() and gateway.alive() and ingest.current.alive()
    # Every transition that reached the robot is on record once, and nothing else is (runs aside).
    records = set(TransitionRecord.objects.filter(id__gt=first_transition, robot_name=ROBOT, source="api",
                                                  run_id="").values_list("id", flat=True))
    assert transitions_reached > 20 and records == record_ids, (transitions_reached, len(records))
    parameters = ParameterRecord.objects.filter(id__gt=first_parameter, robot_name=ROBOT, source="api").count()
    assert parameter_results > 5 and parameters == parameter_results
    print(f"fuzz: seed {SEED}, {REQUESTS} requests in {took:.1f} s, {transitions_reached} transitions and "
          f"{parameter_results} parameter changes reached the robot; answers {sorted(statuses.items())}")
