import pytest


@pytest.fixture(scope="module", autouse=True)
def empty_database(django_db_setup, django_db_blocker):
    """Unit tests start from an empty database (the roles and installed rules as migrations
    leave them). Live tests commit what they store: in one process pytest runs tests/unit before
    them, but in a pytest-xdist worker a live test may have run just before."""
    from django.core.management import call_command

    from tests.conftest import committed_by_live_tests

    if committed_by_live_tests[0]:
        with django_db_blocker.unblock():
            call_command("flush", interactive=False, verbosity=0)
        committed_by_live_tests[0] = False


@pytest.fixture(autouse=True)
def fresh_site_caches():
    """The site's per-process caches (what a token grants, the gateway's heartbeat, the local-memory cache) start empty
    in each test: rolling the database back between tests sends none of the signals that
    would clear them."""
    from django.core.cache import cache

    from lifecycle_site.api.grants import forget
    from lifecycle_site.dashboard import fragments
    from lifecycle_site.gateway_link import gateways

    forget()
    gateways.forget()
    fragments.forget()
    cache.clear()  # what live sockets share (dashboard.socket_checks, snapshots)
    yield
    forget()
    gateways.forget()
    fragments.forget()
    cache.clear()


@pytest.fixture
def gateway_environ(monkeypatch):
    """For a test that starts a RosDomain in this process: RosDomain.start sets the gateway's
    Fast DDS profile in the process's environment, as the gateway process wants; here that
    would reach every process later tests start (a gateway given an interface white list then
    refuses to start, "not both"). monkeypatch puts the environment back afterwards."""
    from ros_gateway.domain import FASTDDS_PROFILES

    monkeypatch.setenv("FASTRTPS_DEFAULT_PROFILES_FILE", str(FASTDDS_PROFILES))
