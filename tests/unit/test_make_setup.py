"""`make setup` (the first step of `make demo`) with a Python that has no ensurepip, as Debian's
without python3.11-venv (issue 26, item 13): it installs the package (here a stand-in installer
that records what it was asked) and goes on to make .venv; a user who cannot install is told
the one command to run (the real .ci/system-packages, as user nobody), and .venv is not tried."""
from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest

from tests.unit.test_system_packages import _as_unprivileged_user

ROOT = Path(__file__).resolve().parents[2]
# A Python whose ensurepip comes only once "$STATE/installed" exists, as Debian's does once
# python3.11-venv is installed; "-m venv" then makes a .venv whose pip only notes its arguments.
FAKE_PYTHON = r"""#!/bin/sh
case "$*" in
  *"import ensurepip"*) [ -e "$STATE/installed" ] && exit 0
                        echo "ModuleNotFoundError: No module named 'ensurepip'" >&2; exit 1 ;;
  *"print("*version_info*) echo "$VERSION"; exit 0 ;;
  "-m venv "*) if [ ! -e "$STATE/installed" ]; then
                 echo "The virtual environment was not created successfully because ensurepip is not available." >&2
                 exit 1
               fi
               mkdir -p "$3/bin"
               printf '#!/bin/sh\necho "pip $*" >> "%s/pip.log"\n' "$STATE" > "$3/bin/pip"
               chmod 755 "$3/bin/pip"; exit 0 ;;
  -c*) exit 0 ;;  # the Makefile's version check
esac
echo "fake python: unexpected arguments: $*" >&2; exit 2
"""
FAKE_INSTALLER = """#!/bin/sh
echo "$*" >> "$STATE/installer.log"
echo "for: $SYSTEM_PACKAGES_FOR" >> "$STATE/installer.log"
touch "$STATE/installed"
"""


@pytest.fixture
def place() -> Path:
    """A directory anyone may read (user nobody runs the fake Python from it)."""
    where = Path(tempfile.mkdtemp(prefix="make-setup-"))
    where.chmod(0o755)
    for name, text in (("python3.11", FAKE_PYTHON), ("installer", FAKE_INSTALLER)):
        (where / name).write_text(text)
        (where / name).chmod(0o755)
    (where / "state").mkdir()
    (where / "state").chmod(0o777)
    yield where
    shutil.rmtree(where)


def test_make_setup_installs_the_missing_venv_package_then_makes_the_venv(place: Path):
    state, venv = place / "state", place / "venv"
    env = {**os.environ, "STATE": str(state), "VERSION": "3.11", "SYSTEM_PACKAGES": str(place / "installer")}
    done = subprocess.run(
        ["make", "--no-print-directory", f"{venv}/bin/.installed", f"VENV={venv}", f"PYTHON={place / 'python3.11'}"],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=60,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert "has no ensurepip" in done.stdout and "python3.11-venv" in done.stdout
    assert (state / "installer.log").read_text().splitlines() == ["python3.11-venv", "for: make demo and make test"]
    assert "pip install --quiet -r requirements-dev.txt" in (state / "pip.log").read_text()
    assert (venv / "bin" / ".installed").exists()


def test_without_root_or_sudo_it_names_the_command_and_makes_no_venv(place: Path):
    """The real installer, as a user who may not install: it stops at once with the command.
    (A version with no such package, so it is missing on this machine whatever is installed.)"""
    state = place / "state"
    script_dir = place / "ci"
    shutil.copytree(ROOT / ".ci", script_dir)
    script_dir.chmod(0o755)
    env = {"PATH": os.environ["PATH"], "STATE": str(state), "VERSION": "3.99"}
    done = subprocess.run(
        [*_as_unprivileged_user(), "env", *[f"{k}={v}" for k, v in env.items()],
         str(script_dir / "python-venv"), str(place / "python3.11")],
        capture_output=True, text=True, timeout=30, cwd="/",
    )
    assert done.returncode == 1, done
    assert "has no ensurepip" in done.stdout
    assert "Debian packages make demo and make test need are not installed: python3.99-venv" in done.stderr
    commands = [line.strip() for line in done.stderr.splitlines() if line.strip().startswith("sudo ")]
    assert commands == [f"sudo {script_dir / 'system-packages'} python3.99-venv"], done.stderr
    assert not (state / "installed").exists()


def test_a_python_with_ensurepip_needs_nothing(place: Path):
    state = place / "state"
    (state / "installed").touch()
    done = subprocess.run([str(ROOT / ".ci" / "python-venv"), str(place / "python3.11")], capture_output=True,
                          text=True, timeout=30, env={**os.environ, "STATE": str(state),
                                                     "SYSTEM_PACKAGES": str(place / "installer")})
    assert (done.returncode, done.stdout, done.stderr) == (0, "", "")
    assert not (state / "installer.log").exists()
