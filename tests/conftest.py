from __future__ import annotations

import re
import time
from pathlib import Path

import pytest
from django.contrib.auth import get_user_model
from django.contrib.auth.models import Group
from django.test import Client

from tests import stack

# Under a failed test, the last lines of every stack process's log written during it (gateway,
# ingest, robots), and its first errors with their tracebacks wherever they are in the log: a
# failure in CI leaves nothing but this output to find the cause in.
FAILURE_LOG_LINES = 40
FAILURE_ERROR_LINES = 200
_STARTED = pytest.StashKey[float]()


def pytest_configure(config):
    # With pytest-xdist (`make test`, TEST_WORKERS=2 by default) each worker is a run of its own (tests/settings.py):
    # the controller, which runs no test, hands back what it drew for itself before they start.
    if config.getoption("dist", default="no") != "no" and not hasattr(config, "workerinput"):
        from tests import settings

        settings.give_back_to_workers()


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item):
    item.stash[_STARTED] = time.time()
    if "live_db" in item.fixturenames:
        committed_by_live_tests[0] = True


# Whether a test that commits what it stores (integration, browser: ``live_db``) ran in this
# process since the database was last emptied: unit tests start from an empty one (tests/unit).
committed_by_live_tests = [False]


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if report.failed and report.when in ("setup", "call"):
        for path in _logs_written_since(item.stash.get(_STARTED, 0.0)):
            lines = path.read_text(errors="replace").splitlines()
            errors = _errors(lines[:-FAILURE_LOG_LINES])
            if errors:
                report.sections.append((f"{path.name}, errors before the last lines", "\n".join(errors)))
            tail = lines[-FAILURE_LOG_LINES:]
            report.sections.append((f"{path.name}, last {len(tail)} lines", "\n".join(tail)))


# Where a log record begins: ours (settings.LOGGING), rclpy's, daphne's access log.
_RECORD_START = re.compile(r"\d{4}-\d\d-\d\d \d\d:|\[(DEBUG|INFO|WARN|ERROR|FATAL)\] |\S+:\d+ - - \[")


def _errors(lines: list[str]) -> list[str]:
    """The lines logged at ERROR or CRITICAL and the lines under each (a traceback), up to
    FAILURE_ERROR_LINES in all."""
    found: list[str] = []
    inside = False
    for line in lines:
        if _RECORD_START.match(line):  # a new record: an error, or the end of the one before
            inside = " ERROR " in line or " CRITICAL " in line or line.startswith(("[ERROR]", "[FATAL]"))
        if inside:
            found.append(line)
            if len(found) >= FAILURE_ERROR_LINES:
                break
    return found


def _logs_written_since(started: float) -> list[Path]:
    directory = stack.log_dir()
    if not directory.is_dir():
        return []
    return sorted(p for p in directory.glob("*.log") if p.stat().st_mtime >= started)


@pytest.fixture(scope="session")
def django_db_setup(django_test_environment, django_db_blocker):
    """Always create the test database file, even when only integration tests run
    (pytest-django would otherwise set up only databases that marked tests use)."""
    from django.test.utils import setup_databases, teardown_databases

    with django_db_blocker.unblock():
        config = setup_databases(verbosity=0, interactive=False, aliases={"default"})
    yield
    with django_db_blocker.unblock():
        _end_other_sessions()
        teardown_databases(config, verbosity=0)


def _end_other_sessions() -> None:
    """On PostgreSQL, end what still holds a session to the test database (a process a test
    killed, whose backend has not noticed yet): DROP DATABASE refuses while any is open."""
    from django.db import connection

    if connection.vendor != "postgresql":
        return
    with connection.cursor() as cursor:
        cursor.execute("SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
                       "WHERE datname = current_database() AND pid <> pg_backend_pid()")


@pytest.fixture(scope="session")
def redis_server():
    """A real Redis of this test run's own, on a free loopback port (a test may stop it and
    start it again: same port, empty, as after a restart without persistence)."""

    def stop(process) -> None:
        process.terminate()
        process.wait(5)

    server = stack.Restartable(stack.start_redis, stop, "Redis")
    server.start()
    yield server
    server.stop()


@pytest.fixture(scope="session")
def live_db(django_db_setup, django_db_blocker):
    """Committed database access shared with the gateway process (no rollback, no flush):
    integration tests keep apart by using robots and domains of their own."""
    django_db_blocker.unblock()
    yield
    django_db_blocker.restore()


_session_ingest: list[stack.Restartable] = []  # the run's ingest process, once a test started it


@pytest.fixture(scope="session")
def ingest(redis_server, live_db):
    """The site's ingest process, one for the whole run (defined here, once, so that every
    test directory shares it): it stores what every gateway reports
    (a test may stop it for a while and start it again)."""
    count = 0

    def start() -> stack.Process:
        nonlocal count
        count += 1
        process = stack.start_ingest(f"ingest-{count}")
        stack.wait_for(lambda: "ingest is running" in process.output() or not process.alive(), 30,
                       "the ingest process to start")
        assert process.alive(), process.output()
        return process

    def stop(process: stack.Process) -> None:
        assert process.stop() == 0, process.output()

    holder = stack.Restartable(start, stop, "the ingest process")
    holder.start()
    _session_ingest.append(holder)
    yield holder
    _session_ingest.clear()
    holder.stop()


@pytest.fixture(scope="module")
def live_ingest_set_aside():
    """For unit tests that drive Ingest objects of their own on this run's Redis and database:
    the run's ingest process, if a live test in this process started it (pytest-xdist runs test
    files in any order), would take their lease and read their streams. It is stopped for the
    module and started again after it."""
    holder = _session_ingest[0] if _session_ingest else None
    running = holder is not None and holder.current is not None
    if running:
        holder.stop()
    yield
    if running:
        holder.start()


def session_of(user):
    """A logged-in session of ``user`` (what a WebSocket's scope carries from the browser)."""
    client = Client()
    client.force_login(user)
    return client.session


def make_user(username: str, role: str | None):
    user = get_user_model().objects.filter(username=username).first()
    if user is None:
        user = get_user_model().objects.create_user(username, password="a-test-password-123")
    if role:
        user.groups.add(Group.objects.get(name=role))
    return user


def client_of(username: str, role: str | None) -> Client:
    """A test client of the site (this test process) logged in as ``username`` with ``role``."""
    client = Client()
    client.force_login(make_user(username, role))
    return client


@pytest.fixture
def operator_client(db) -> Client:
    return client_of("olga-operator", "operator")


@pytest.fixture
def viewer_client(db) -> Client:
    return client_of("victor-viewer", "viewer")


@pytest.fixture(scope="module")
def gateway(redis_server, live_db, ingest):
    """The gateway "local" on this run's Redis, one per test module (integration and deploy tests)."""
    from lifecycle_site.gateway_link import gateways

    process = stack.start_gateway()
    stack.wait_for(lambda: gateways.status("local").online or not process.alive(), 30, "the gateway heartbeat")
    assert process.alive(), process.output()
    yield process
    process.stop()


@pytest.fixture(scope="module")
def api(live_db) -> Client:
    """A logged-in operator's test client of the site (this test process)."""
    return client_of("ivan-operator", "operator")
