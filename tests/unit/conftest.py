import pytest


@pytest.fixture(autouse=True)
def fresh_site_caches():
    """The site's per-process caches (what a token grants, the gateway's heartbeat) start empty
    in each test: rolling the database back between tests sends none of the signals that
    would clear them."""
    from lifecycle_site.api.grants import forget
    from lifecycle_site.fleet import gateways

    forget()
    gateways.forget()
    yield
    forget()
    gateways.forget()
