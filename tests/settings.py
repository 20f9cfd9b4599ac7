"""Test settings: the product's settings, pointed at a scratch data dir, a Redis port and a
range of ROS domains of this test run's own. Subprocesses (gateway, daphne) get the same
values through ``tests.stack.environment()``."""
import os
import socket
import tempfile


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


DOMAIN_BLOCK = 45  # ROS domains of one run: tests.stack.domain(0) to domain(44)

# Set once per run (the values travel to pytest's subprocesses through the environment). Each
# pytest-xdist worker is a run of its own: it draws its own scratch dir, Redis port, ROS domains and
# database instead of sharing those its controller drew; what a worker starts inherits the worker's.
_run = os.environ.get("PYTEST_XDIST_WORKER", "main")
if os.environ.get("LIFECYCLE_TEST_RUN", _run) != _run:
    for _key in ("LIFECYCLE_DATA_DIR", "REDIS_URL", "LIFECYCLE_TEST_DOMAIN_BASE", "ROS_DOMAIN_ID", "DATABASE_URL"):
        os.environ.pop(_key, None)
os.environ["LIFECYCLE_TEST_RUN"] = _run
if "LIFECYCLE_DATA_DIR" not in os.environ:  # the run's first process: its scratch dir, gone with it
    import atexit
    import shutil

    os.environ["LIFECYCLE_DATA_DIR"] = tempfile.mkdtemp(prefix="lifecycle-test-")
    atexit.register(shutil.rmtree, os.environ["LIFECYCLE_DATA_DIR"], ignore_errors=True)
os.environ.setdefault("REDIS_URL", f"redis://127.0.0.1:{_free_port()}/0")
if "LIFECYCLE_TEST_DOMAIN_BASE" not in os.environ:  # the run's first process claims them
    from tests import domains

    # Offsets 0-44 (tests.stack.domain): one of four blocks of 45 of the domains 30-119 and 132-221,
    # held for the run's life (the benchmarks take 120-131, and may run beside a test run). Those
    # above 101 come second: their DDS ports lie in Linux's ephemeral range, where a free port drawn
    # for a server may meet them. An xdist controller gives its block back (tests/conftest.py).
    os.environ["LIFECYCLE_TEST_DOMAIN_BASE"] = str(domains.claim_block(DOMAIN_BLOCK, (30, 120), (132, 222)))
os.environ.setdefault("LIFECYCLE_CHANNEL_PREFIX", "lifecycle-test")
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", os.environ["LIFECYCLE_TEST_DOMAIN_BASE"])
# Quicker loops than in production, so tests wait less.
os.environ.setdefault("LIFECYCLE_DISCOVERY_INTERVAL", "0.2")
os.environ.setdefault("LIFECYCLE_ROBOT_REFRESH_INTERVAL", "0.5")
os.environ.setdefault("LIFECYCLE_HEARTBEAT_INTERVAL", "0.5")
os.environ.setdefault("LIFECYCLE_GATEWAY_OFFLINE_AFTER", "3")
os.environ.setdefault("LIFECYCLE_SERVICE_TIMEOUT", "3")
# The tests' webhook receivers listen on loopback, which webhooks may reach only when listed.
os.environ.setdefault("LIFECYCLE_WEBHOOK_ALLOW", "127.0.0.1")
# LIFECYCLE_TEST_DATABASE=postgres (`make test-postgres`): a throw-away PostgreSQL cluster for the
# run, stopped and removed when this process ends (tests/postgres.py); every child process
# gets its DATABASE_URL. The run's first process starts it; the URL travels to the others.
if os.environ.get("LIFECYCLE_TEST_DATABASE", "sqlite") == "postgres" and not os.environ.get(
        "DATABASE_URL", "").startswith("postgres"):
    import atexit

    from tests.postgres import Cluster

    _cluster = Cluster()
    os.environ["DATABASE_URL"] = _cluster.start()
    atexit.register(_cluster.stop)
elif os.environ.get("LIFECYCLE_TEST_DATABASE", "sqlite") not in ("sqlite", "postgres"):
    raise RuntimeError(f"LIFECYCLE_TEST_DATABASE={os.environ['LIFECYCLE_TEST_DATABASE']!r}: use 'sqlite' (the "
                       "default) or 'postgres'")
os.environ.setdefault("DATABASE_URL", f"sqlite:///{os.environ['LIFECYCLE_DATA_DIR']}/test.sqlite3")

from lifecycle_site.settings import *  # noqa: E402,F401,F403
from lifecycle_site.settings import DATABASES  # noqa: E402

# pytest-django creates this file (not an in-memory DB), or this database on PostgreSQL, under the
# name the URL gives: other processes share it.
DATABASES["default"]["TEST"] = {"NAME": DATABASES["default"]["NAME"]}


def give_back_to_workers() -> None:
    """An xdist controller runs no test: its ROS domains and database go before it starts the
    workers, which draw their own."""
    from tests import domains

    base = int(os.environ.pop("LIFECYCLE_TEST_DOMAIN_BASE"))
    domains.release(list(range(base, base + DOMAIN_BLOCK)))
    if "_cluster" in globals():
        _cluster.stop()
