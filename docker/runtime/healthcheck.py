"""Docker HEALTHCHECK of the image; what "healthy" means depends on the container's role.

web      the site answers GET /healthz (with a Host it accepts) with a non-error status
ingest   the ingest lease in Redis is held (P:site:ingest:lease)
gateway  its heartbeat in Redis (P:gw:NAME:beat) is fresh and written from this container
redis    redis-server answers PING
robot    the process runs (the container would have exited otherwise)

P is LIFECYCLE_CHANNEL_PREFIX. Standard library only, except redis-py for the Redis URLs of
ingest and gateway (their TLS and credentials as the processes read them), so a check costs
a few MB inside the container's memory limit. No check opens the database.
"""
from __future__ import annotations

import json
import os
import socket
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

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
        f"http://127.0.0.1:{details.get('port', '8000')}/healthz", headers={"Host": host}
    )
    try:
        with urllib.request.urlopen(request, timeout=8) as response:
            status = response.status
    except urllib.error.HTTPError as exc:
        status = exc.code
    except (urllib.error.URLError, OSError) as exc:
        return f"site does not answer: {exc}"
    return None if status < 400 else f"GET /healthz answered {status}"


def _redis(url: str):
    """A client as the processes make them (redis-py reads rediss:// and its ssl_* parameters)."""
    import redis

    return redis.Redis.from_url(url, socket_connect_timeout=4, socket_timeout=4)


def _prefix(details: dict[str, str]) -> str:
    return details.get("prefix") or os.environ.get("LIFECYCLE_CHANNEL_PREFIX", "lifecycle")


def gateway_redis_url() -> str:
    """The Redis URL the gateway process got: from the app configuration (cfg-data: redis.*,
    which wins, as in the entrypoint) or the container's environment. Read again here rather
    than written anywhere by the entrypoint: the URL holds the gateway's password."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import config

    return config.gateway_env(config.read_config()).get("REDIS_URL") or os.environ.get(
        "REDIS_URL", "redis://127.0.0.1:6379/0")


def check_gateway(details: dict[str, str]) -> str | None:
    """Its heartbeat key in Redis is fresh (as the site judges it) and written from this
    container. With the gateway's own Redis user: it may read its own keys, nothing else.
    The database is not looked at: a gateway has none."""
    import redis

    name = details.get("gateway") or os.environ.get("LIFECYCLE_GATEWAY_NAME", "local")
    limit = float(os.environ.get("LIFECYCLE_GATEWAY_OFFLINE_AFTER", 10))
    key = f"{_prefix(details)}:gw:{name}:beat"
    try:
        url = gateway_redis_url()
    except Exception as exc:  # noqa: BLE001 - config.ConfigError: the entrypoint refused it too
        return f"the configuration is not usable: {exc}"
    try:
        raw = _redis(url).get(key)
    except redis.RedisError as exc:
        return f"cannot read the heartbeat {key}: {exc}"
    if raw is None:
        return f"no heartbeat of gateway {name!r} ({key}) in Redis"
    try:
        beat = json.loads(raw)
        age = time.time() - float(beat["at"])
    except (ValueError, TypeError, KeyError) as exc:
        return f"unreadable heartbeat {key}: {exc}"
    if beat.get("stopped"):
        return f"gateway {name!r} said it stopped {age:.0f} s ago"
    if beat.get("host") != socket.gethostname():
        return f"gateway {name!r} beats from {beat.get('host')!r}, not from this container"
    return None if age < limit else f"last heartbeat {age:.0f} s ago (offline after {limit:g} s)"


def check_ingest(details: dict[str, str]) -> str | None:
    """The ingest lease is held (by this container's process, or by another ingest process
    while this one stands by): someone stores what the gateways report."""
    import redis

    key = f"{_prefix(details)}:site:ingest:lease"
    try:
        holder = _redis(os.environ.get("REDIS_URL", "redis://127.0.0.1:6379/0")).get(key)
    except redis.RedisError as exc:
        return f"cannot read the ingest lease {key}: {exc}"
    return None if holder else f"nobody holds the ingest lease ({key})"


def check_redis() -> str | None:
    """PING answers PONG (after AUTH when the default user has a password)."""
    password = os.environ.get("REDIS_PASSWORD", "")
    commands = ([["AUTH", password]] if password else []) + [["PING"]]
    request = b"".join(
        b"*%d\r\n" % len(words) + b"".join(b"$%d\r\n%s\r\n" % (len(w.encode()), w.encode()) for w in words)
        for words in commands
    )
    try:
        with socket.create_connection(("127.0.0.1", 6379), timeout=5) as conn:
            conn.sendall(request)
            reply = b""
            while reply.count(b"\r\n") < len(commands):
                chunk = conn.recv(256)
                if not chunk:
                    break
                reply += chunk
    except OSError as exc:
        return f"redis does not answer: {exc}"
    last = reply.split(b"\r\n")[len(commands) - 1] if reply.count(b"\r\n") >= len(commands) else reply
    return None if last.startswith(b"+PONG") else f"unexpected reply {reply[:80]!r}"


def main() -> int:
    details = info()
    role = details.get("role", "")
    if role == "web":
        problem = check_web(details)
    elif role == "gateway":
        problem = check_gateway(details)
    elif role == "ingest":
        problem = check_ingest(details)
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
