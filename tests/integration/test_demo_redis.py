"""A second demo does not share the first one's Redis (issue 26, item 14): two sites on one
Redis take each other's gateway commands and facts. It refuses with the reason and the way out,
and with a Redis of its own it runs. Real `manage.py run_demo` processes (without robots) and real
Redis servers; DDS stays on loopback."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import redis
from django.core.management.base import CommandError
from django.test import override_settings

from lifecycle_site import local_redis
from lifecycle_site.fleet.management.commands.run_demo import Command
from tests import stack


def redis_dir(url: str) -> Path:
    """Where the Redis at ``url`` keeps its files (the data dir of the demo that started it)."""
    return Path(redis.Redis.from_url(url).config_get("dir")["dir"]).resolve()


def demo_env(data_dir: Path, redis_url: str) -> dict[str, str]:
    env = dict(os.environ)
    for name in ("DATABASE_URL", "DJANGO_ALLOW_ASYNC_UNSAFE"):  # each demo keeps its own SQLite
        env.pop(name, None)
    env.update(
        DJANGO_SETTINGS_MODULE="lifecycle_site.settings",
        LIFECYCLE_DATA_DIR=str(data_dir),
        REDIS_URL=redis_url,
        DEMO_DOMAIN_AGV1=str(stack.domain(30)),
        DEMO_DOMAIN_AGV2=str(stack.domain(31)),
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        PYTHONUNBUFFERED="1",
    )
    return env


def run_demo(data_dir: Path, redis_url: str, out: Path, *extra: str) -> subprocess.Popen:
    with open(out, "wb") as sink:
        return subprocess.Popen(
            [sys.executable, "manage.py", "run_demo", "--no-robots", "--port", str(stack.free_port()), *extra],
            cwd=stack.ROOT, env=demo_env(data_dir, redis_url), stdout=sink, stderr=subprocess.STDOUT,
            start_new_session=True,
        )


@pytest.fixture
def first_demo(tmp_path: Path):
    """A demo running from data dir "first", with the Redis it started at a free port."""
    url = f"redis://127.0.0.1:{stack.free_port()}/0"
    data, out = tmp_path / "first", tmp_path / "first.out"
    demo = run_demo(data, url, out)
    try:
        stack.wait_for(lambda: "Lifecycle manager running at" in out.read_text() or demo.poll() is not None,
                       90, "the first demo to print its URL")
        assert demo.poll() is None, out.read_text()
        yield data, url, demo.pid
    finally:
        if demo.poll() is None:
            os.killpg(demo.pid, signal.SIGINT)  # Ctrl-C: it stops its children and its Redis
            try:
                demo.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(demo.pid, signal.SIGKILL)
                demo.wait(5)


def test_a_second_demo_refuses_the_first_ones_redis_and_runs_with_its_own(first_demo, tmp_path: Path):
    first, url, pid = first_demo
    assert redis_dir(url) == (first / "redis").resolve()

    out = tmp_path / "second.out"
    second = run_demo(tmp_path / "second", url, out, "--check")
    assert second.wait(60) != 0, out.read_text()  # before: it ran on the first one's Redis
    said = " ".join(out.read_text().split())
    assert f"The Redis at {url} is the one of the demo running from {first} (pid {pid})" in said, said
    assert "two sites on one Redis" in said and "REDIS_URL=redis://127.0.0.1:" in said, said
    assert "Lifecycle manager running at" not in said

    # With a Redis of its own (the way out it names), it runs beside the first.
    own_url = f"redis://127.0.0.1:{stack.free_port()}/0"
    out = tmp_path / "second-own.out"
    second = run_demo(tmp_path / "second", own_url, out, "--check")
    assert second.wait(90) == 0, out.read_text()
    assert "Lifecycle manager running at" in out.read_text()
    assert redis_dir(url) == (first / "redis").resolve()  # the first one's is untouched
    assert f"Starting Redis on 127.0.0.1:{own_url.split(':')[2].split('/')[0]}" in out.read_text()


def test_at_the_default_address_a_redis_not_its_own_is_refused_one_named_on_purpose_is_taken(tmp_path: Path):
    """No REDIS_URL set: a Redis answering where the demo's own would be must be this data dir's."""
    port = stack.free_port()
    other = local_redis.start(port, tmp_path / "someone-elses")
    url = f"redis://127.0.0.1:{port}/0"
    try:
        with override_settings(REDIS_URL=url):
            with pytest.raises(CommandError, match=r"not this demo's \(it keeps its files in .*someone-elses"):
                Command()._ensure_redis(tmp_path / "demo", chosen=False)
            assert Command()._ensure_redis(tmp_path / "demo", chosen=True) is None  # REDIS_URL names it
            own_port = stack.free_port()
            own = local_redis.start(own_port, tmp_path / "demo" / "redis")
            try:
                with override_settings(REDIS_URL=f"redis://127.0.0.1:{own_port}/0"):
                    assert Command()._ensure_redis(tmp_path / "demo", chosen=False) is None  # its own
            finally:
                own.kill()
                own.wait(5)
    finally:
        other.kill()
        other.wait(5)
