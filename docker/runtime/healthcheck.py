"""Docker HEALTHCHECK of the image; what "healthy" means depends on the container's role.

web      the site answers GET /login/ (with a Host it accepts) with a non-error status
gateway  the gateway wrote its heartbeat into the database recently
redis    redis-server answers PING
robot    the process runs (the container would have exited otherwise)

Standard library only, so that a check costs a few MB inside the container's memory limit.
"""
from __future__ import annotations

import os
import socket
import sqlite3
import sys
import urllib.error
import urllib.request
from datetime import datetime, timezone
from pathlib import Path
from urllib.parse import urlparse

INFO = Path("/tmp/lifecycle-health")


def info() -> dict[str, str]:
    try:
        lines = INFO.read_text().splitlines()
    except OSError:
        return {}
    return dict(line.split("=", 1) for line in lines if "=" in line)


def check_web(details: dict[str, str]) -> str | None:
    hosts = [h.strip() for h in details.get("allowed_hosts", "").split(",") if h.strip()]
    host = next((h for h in hosts if h != "*"), "localhost")
    if host.startswith("."):  # ".plant.local" allows any subdomain
        host = "health" + host
    request = urllib.request.Request(
        f"http://127.0.0.1:{details.get('port', '8000')}/login/", headers={"Host": host}
    )
    try:
        with urllib.request.urlopen(request, timeout=8) as response:
            status = response.status
    except urllib.error.HTTPError as exc:
        status = exc.code
    except (urllib.error.URLError, OSError) as exc:
        return f"site does not answer: {exc}"
    return None if status < 400 else f"GET /login/ answered {status}"


def check_gateway() -> str | None:
    url = os.environ.get("DATABASE_URL", "")
    if url and not url.startswith("sqlite:"):
        return None  # another database: the restart policy watches the process
    path = urlparse(url).path if url else str(Path(os.environ.get("LIFECYCLE_DATA_DIR", "/data")) / "db.sqlite3")
    name = os.environ.get("LIFECYCLE_GATEWAY_NAME", "gateway")
    limit = float(os.environ.get("LIFECYCLE_GATEWAY_OFFLINE_AFTER", 10)) * 3
    try:
        with sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=5) as db:
            row = db.execute("SELECT last_beat FROM fleet_gatewayheartbeat WHERE name = ?", (name,)).fetchone()
    except sqlite3.Error as exc:
        return f"cannot read the heartbeat: {exc}"
    if row is None:
        return f"no heartbeat of gateway {name!r} yet"
    beat = datetime.fromisoformat(str(row[0]))
    if beat.tzinfo is None:
        beat = beat.replace(tzinfo=timezone.utc)
    age = (datetime.now(timezone.utc) - beat).total_seconds()
    return None if age < limit else f"last heartbeat {age:.0f} s ago"


def check_redis() -> str | None:
    try:
        with socket.create_connection(("127.0.0.1", 6379), timeout=5) as conn:
            conn.sendall(b"PING\r\n")
            reply = conn.recv(64)
    except OSError as exc:
        return f"redis does not answer: {exc}"
    return None if reply.startswith(b"+PONG") else f"unexpected reply {reply!r}"


def main() -> int:
    details = info()
    role = details.get("role", "")
    if role == "web":
        problem = check_web(details)
    elif role == "gateway":
        problem = check_gateway()
    elif role == "redis":
        problem = check_redis()
    elif role == "robot":
        problem = None
    else:
        problem = "still starting (no role recorded yet)"
    if problem:
        print(f"unhealthy ({role or 'unknown'}): {problem}")
        return 1
    print(f"healthy ({role})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
