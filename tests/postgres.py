"""A throw-away PostgreSQL cluster for a test or benchmark run: Debian's server binaries, a
temporary directory, loopback only, a free port, a password made for this run, fsync off.

``Cluster.start()`` returns the DATABASE_URL; ``stop()`` stops the server and removes its
directory. A guardian process (``python -m tests.postgres guard PID DIR``) does the same when
the process that started the cluster dies without stopping it (killed, or ended by a signal).

initdb and postgres refuse to run as root: as root the cluster runs as the ``postgres`` system
user (Debian's package makes it), in a directory that user owns.
"""
from __future__ import annotations

import glob
import os
import pwd
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

USER = "lifecycle"
DATABASE = "lifecycle_test"
# Two site instances (up to 64 request threads each, lifecycle_site/http_handler.py), the
# ingest process, the test process and a benchmark's clients, with room to spare.
MAX_CONNECTIONS = 300


class ClusterError(RuntimeError):
    """The cluster could not be made or started; the message says why and what to do."""


def server_bin() -> Path:
    """Debian's PostgreSQL server binaries (postgresql-NN), the newest installed; or $PG_BIN."""
    if os.environ.get("PG_BIN"):
        return Path(os.environ["PG_BIN"])
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), key=lambda p: int(Path(p).parts[-3]))
    if not found:
        raise ClusterError(
            "PostgreSQL's server is not installed (no /usr/lib/postgresql/*/bin/initdb): install Debian's "
            "'postgresql' package (`make system-packages` does), or set PG_BIN to the directory of initdb."
        )
    return Path(found[-1]).parent


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _as_owner() -> list[str]:
    """The prefix that runs a command as the cluster's owner: ``postgres`` when we are root."""
    if os.geteuid() != 0:
        return []
    try:
        owner = pwd.getpwnam("postgres")
    except KeyError:
        raise ClusterError("running as root, and there is no 'postgres' system user to run the test cluster "
                           "as (Debian's postgresql package makes it): install that package") from None
    return ["setpriv", f"--reuid={owner.pw_uid}", f"--regid={owner.pw_gid}", "--init-groups"]


class Cluster:
    def __init__(self, max_connections: int = MAX_CONNECTIONS) -> None:
        self.max_connections = max_connections
        self.dir: Path | None = None
        self.port = 0
        self.url = ""
        self._guard: subprocess.Popen | None = None

    def start(self) -> str:
        bin_dir = server_bin()
        self.dir = Path(tempfile.mkdtemp(prefix="lifecycle-pg-"))
        try:
            return self._start(bin_dir)
        except BaseException:
            self.stop()
            raise

    def _start(self, bin_dir: Path) -> str:
        assert self.dir is not None
        prefix = _as_owner()
        if prefix:
            owner = pwd.getpwnam("postgres")
            os.chown(self.dir, owner.pw_uid, owner.pw_gid)
        self._guard = subprocess.Popen(
            [sys.executable, "-m", "tests.postgres", "guard", str(os.getpid()), str(self.dir), str(bin_dir)],
            cwd=Path(__file__).resolve().parents[1], start_new_session=True,
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )
        password = secrets.token_urlsafe(24)
        password_file = self.dir / "password"
        password_file.write_text(password + "\n")
        if prefix:
            os.chown(password_file, owner.pw_uid, owner.pw_gid)
        password_file.chmod(0o600)
        data = self.dir / "data"
        self._run(prefix + [str(bin_dir / "initdb"), "-D", str(data), "-U", USER, f"--pwfile={password_file}",
                            "--auth=scram-sha-256", "--encoding=UTF8", "--locale=C.UTF-8", "--no-sync"], "initdb")
        password_file.unlink()
        self.port = _free_port()
        options = " ".join([
            "-c listen_addresses=127.0.0.1", f"-p {self.port}", f"-c unix_socket_directories={self.dir}",
            f"-c max_connections={self.max_connections}",
            # A throw-away cluster: nothing needs to survive a crash of this machine.
            "-c fsync=off", "-c synchronous_commit=off", "-c full_page_writes=off",
        ])
        self._run(prefix + [str(bin_dir / "pg_ctl"), "-D", str(data), "-l", str(self.dir / "server.log"),
                            "-o", options, "-w", "-t", "60", "start"], "pg_ctl start")
        self.url = f"postgres://{USER}:{password}@127.0.0.1:{self.port}/{DATABASE}"
        return self.url

    def _run(self, argv: list[str], what: str) -> None:
        done = subprocess.run(argv, capture_output=True, text=True, timeout=120, cwd=self.dir)
        if done.returncode != 0:
            log = self.dir / "server.log" if self.dir else None
            tail = log.read_text(errors="replace")[-2000:] if log and log.exists() else ""
            raise ClusterError(f"{what} failed for the test PostgreSQL cluster (exit {done.returncode}):\n"
                               f"{done.stdout}{done.stderr}{tail}")

    def stop(self) -> None:
        if self.dir is not None:
            stop_cluster(self.dir, server_bin())
            self.dir = None
        if self._guard is not None:
            self._guard.terminate()
            self._guard.wait(10)
            self._guard = None


def stop_cluster(where: Path, bin_dir: Path) -> None:
    """Stop the server of the cluster in ``where`` (if it runs) and remove the directory."""
    data = where / "data"
    if (data / "postmaster.pid").exists():
        done = subprocess.run(_as_owner() + [str(bin_dir / "pg_ctl"), "-D", str(data), "-m", "fast", "-w",
                                             "-t", "30", "stop"], capture_output=True, timeout=60)
        if done.returncode != 0 and (data / "postmaster.pid").exists():
            try:  # the first line of postmaster.pid is the server's pid
                os.kill(int((data / "postmaster.pid").read_text().split()[0]), signal.SIGKILL)
            except (ValueError, IndexError, ProcessLookupError):
                pass
    shutil.rmtree(where, ignore_errors=True)


def _guard(pid: int, where: Path, bin_dir: Path) -> None:
    """Wait for ``pid`` to end, then stop and remove the cluster if it is still there."""
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))  # the owner stopped the cluster itself
    while where.exists():
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            stop_cluster(where, bin_dir)
            return
        time.sleep(1)


if __name__ == "__main__" and sys.argv[1:2] == ["guard"]:
    _guard(int(sys.argv[2]), Path(sys.argv[3]), Path(sys.argv[4]))
