"""lifecycle_site/web_processes.py: which daphne options several processes can serve, and the
refusals for those they cannot (the processes themselves: tests/integration/test_web_processes.py)."""
from __future__ import annotations

import pytest

from lifecycle_site import web_processes
from lifecycle_site.web_processes import LaunchRefused, split_options


def test_the_address_is_taken_out_and_every_other_option_passed_on():
    listener = split_options(["--proxy-headers", "-b", "0.0.0.0", "--port=8123", "-v", "1",
                              "lifecycle_site.asgi:application"])
    assert (listener.host, listener.port) == ("0.0.0.0", 8123)
    assert listener.passed == ["--proxy-headers", "-v", "1", "lifecycle_site.asgi:application"]


def test_daphnes_own_defaults_when_no_address_is_given():
    listener = split_options(["lifecycle_site.asgi:application"])
    assert (listener.host, listener.port) == ("127.0.0.1", 8000)


@pytest.mark.parametrize("options, says", [
    (["-u", "/run/site.sock"], "-u is not supported"),
    (["--fd", "3"], "--fd is not supported"),
    (["-e", "tcp:8000"], "-e is not supported"),
    (["-b", "::1", "-p", "8000"], "IPv4 only"),
    (["-p", "eighty"], "port 'eighty' is not a number"),
])
def test_what_several_processes_cannot_serve_is_refused_with_what_to_change(options, says):
    with pytest.raises(LaunchRefused) as refused:
        split_options([*options, "lifecycle_site.asgi:application"])
    assert says in str(refused.value)
    assert "LIFECYCLE_WEB_PROCESSES" in str(refused.value) or "not a number" in str(refused.value)


def test_an_address_in_use_is_refused_by_name(tmp_path):
    first = web_processes.bind(split_options(["-b", "127.0.0.1", "-p", "0"]))
    try:
        port = first.getsockname()[1]
        with pytest.raises(LaunchRefused, match=f"Cannot listen on 127.0.0.1:{port}"):
            web_processes.bind(split_options(["-b", "127.0.0.1", "-p", str(port)]))
    finally:
        first.close()
