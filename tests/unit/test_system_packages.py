"""`.ci/system-packages` (what `make test` runs first), run for real by a user with neither
root nor sudo: it must not try to install, and must print the one command that would."""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / ".ci" / "system-packages"
NOBODY = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"]
NOT_A_PACKAGE = "lifecycle-test-no-such-package"


def _as_unprivileged_user() -> list[str]:
    """The prefix that runs a command as a user with neither root nor sudo."""
    if os.geteuid() == 0:
        return NOBODY
    if shutil.which("sudo") and subprocess.run(["sudo", "-n", "true"], capture_output=True).returncode == 0:
        return ["sudo", "-n", *NOBODY]
    return []  # we are such a user already


@pytest.fixture
def script() -> Path:
    """A copy that user 'nobody' can read, wherever the checkout is."""
    where = Path(tempfile.mkdtemp(prefix="system-packages-"))
    where.chmod(0o755)
    copy = where / "system-packages"
    shutil.copy(SCRIPT, copy)
    copy.chmod(0o755)
    yield copy
    shutil.rmtree(where)


def run(script: Path, *packages: str) -> tuple[subprocess.CompletedProcess, float]:
    started = time.monotonic()
    done = subprocess.run(
        [*_as_unprivileged_user(), str(script), *packages], capture_output=True, text=True, timeout=30, cwd="/"
    )
    return done, time.monotonic() - started


def test_missing_package_without_root_or_sudo_stops_at_once_with_the_command(script):
    done, took = run(script, "bash", NOT_A_PACKAGE)
    assert done.returncode == 1, done
    assert "Installing the Debian packages" not in done.stdout  # it did not go on to apt-get
    assert f"not installed: {NOT_A_PACKAGE}\n" in done.stderr
    commands = [line.strip() for line in done.stderr.splitlines() if line.strip().startswith("sudo ")]
    assert commands == [f"sudo {script} bash {NOT_A_PACKAGE}"], done.stderr
    assert took < 5


def test_all_present_needs_no_privileges(script):
    done, took = run(script, "bash", "dpkg")  # both are Essential on Debian
    assert done.returncode == 0, done
    assert done.stdout.strip() == "System packages the tests need: all present (bash dpkg)."
    assert took < 5


def test_the_list_has_the_servers_the_tests_start():
    """Redis, nginx and PostgreSQL (the second integration run's throw-away cluster,
    tests/postgres.py) are started by the tests themselves; Chromium by the browser tests."""
    listed = re.search(r"^PACKAGES=\(([^)]*)\)", SCRIPT.read_text(), re.MULTILINE).group(1).split()
    assert {"redis-server", "nginx", "postgresql", "chromium"} <= set(listed), listed
