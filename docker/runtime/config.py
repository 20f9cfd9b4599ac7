"""Apply the app configuration at container start (called by entrypoint.sh).

The configuration file ($LIFECYCLE_CONFIG_FILE, default /cfg-data/param.json) is what the
Industrial Edge Management writes from the JSON-Forms template (docker/edge/cfg-data-template):

    {
      "admin":  {"username": "admin", "password": "...", "email": ""},
      "site":   {"allowedHosts": "ied-1.plant.local", "csrfTrustedOrigins": "", "urlPrefix": "/lifecycle",
                 "behindTlsProxy": true, "timeZone": "Europe/Berlin", "logLevel": "INFO"},
      "ros":    {"discoveryRange": "SUBNET", "staticPeers": "", "serviceTimeout": 5},
      "robots": [{"name": "agv-1", "domainId": 21, "namespace": "", "description": "", "enabled": true}]
    }

Every part is optional; an empty value leaves the environment's value in force.

    config.py env [ROLE]           print `export NAME='value'` lines for the settings (no Django)
    config.py setup                migrate, create/update the admin account, register the robots
                                   (all of the gateway "local", the one the site's compose runs)
    config.py wait-for-schema N    wait up to N seconds until the web container has migrated (ingest)
"""
from __future__ import annotations

import json
import os
import re
import secrets
import shlex
import sys
import time
from pathlib import Path

CONFIG_FILE = Path(os.environ.get("LIFECYCLE_CONFIG_FILE", "/cfg-data/param.json"))
DISCOVERY_RANGES = ("SUBNET", "LOCALHOST", "OFF", "SYSTEM_DEFAULT")
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")
# The gateway the site's own compose file runs; robots of other gateways (cells) are added with
# `manage.py add_robot NAME --domain N --gateway CELL` or in the admin.
LOCAL_GATEWAY = "local"


class ConfigError(Exception):
    pass


def log(message: str) -> None:
    print(f"config: {message}", file=sys.stderr, flush=True)


def read_config() -> dict:
    if not CONFIG_FILE.is_file():
        return {}
    try:
        data = json.loads(CONFIG_FILE.read_text(encoding="utf-8") or "{}")
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{CONFIG_FILE} is not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{CONFIG_FILE} must hold a JSON object")
    for part in ("admin", "site", "ros"):
        if not isinstance(data.get(part, {}), dict):
            raise ConfigError(f"{CONFIG_FILE}: '{part}' must be an object")
    if not isinstance(data.get("robots", []), list):
        raise ConfigError(f"{CONFIG_FILE}: 'robots' must be a list")
    return data


def _text(value) -> str:
    if isinstance(value, list):
        return ",".join(str(v).strip() for v in value if str(v).strip())
    return "" if value is None else str(value).strip()


def _comma_list(value) -> str:
    items = value if isinstance(value, list) else _text(value).split(",")
    return ",".join(str(item).strip() for item in items if str(item).strip())


def settings_env(config: dict) -> dict[str, str]:
    """The environment variables the configuration sets (only those with a value)."""
    site, ros = config.get("site", {}), config.get("ros", {})
    env: dict[str, str] = {}

    def put(name: str, value) -> None:
        text = _text(value)
        if text:
            env[name] = text

    put("DJANGO_ALLOWED_HOSTS", _comma_list(site.get("allowedHosts")))
    put("DJANGO_CSRF_TRUSTED_ORIGINS", _comma_list(site.get("csrfTrustedOrigins")))
    prefix = _text(site.get("urlPrefix"))
    if prefix:
        if not re.fullmatch(r"(/[A-Za-z0-9._~-]+)+/?", prefix):
            raise ConfigError(f"site.urlPrefix {prefix!r} must look like /lifecycle")
        env["LIFECYCLE_URL_PREFIX"] = prefix.rstrip("/")
    if isinstance(site.get("behindTlsProxy"), bool):
        env["LIFECYCLE_BEHIND_TLS_PROXY"] = "1" if site["behindTlsProxy"] else "0"
    put("TZ", site.get("timeZone"))
    level = _text(site.get("logLevel")).upper()
    if level:
        if level not in LOG_LEVELS:
            raise ConfigError(f"site.logLevel must be one of {', '.join(LOG_LEVELS)}")
        env["LIFECYCLE_LOG_LEVEL"] = level
    scope = _text(ros.get("discoveryRange")).upper()
    if scope:
        if scope not in DISCOVERY_RANGES:
            raise ConfigError(f"ros.discoveryRange must be one of {', '.join(DISCOVERY_RANGES)}")
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = scope
    peers = ros.get("staticPeers")
    if isinstance(peers, list):
        peers = ";".join(str(p).strip() for p in peers if str(p).strip())
    put("ROS_STATIC_PEERS", _text(peers).replace(",", ";"))
    timeout = ros.get("serviceTimeout")
    if timeout not in (None, ""):
        try:
            if float(timeout) <= 0:
                raise ValueError
        except (TypeError, ValueError):
            raise ConfigError("ros.serviceTimeout must be a positive number of seconds") from None
        env["LIFECYCLE_SERVICE_TIMEOUT"] = str(float(timeout))
    return env


def robots_wanted(config: dict) -> list[dict]:
    """Robots from the configuration file plus LIFECYCLE_ROBOTS ("agv-1:21[:/ns],agv-2:22")."""
    robots = []
    for index, item in enumerate(config.get("robots", [])):
        if not isinstance(item, dict) or not _text(item.get("name")) or item.get("domainId") in (None, ""):
            raise ConfigError(f"robots[{index}] needs a name and a domainId")
        try:
            domain = int(item["domainId"])
        except (TypeError, ValueError):
            raise ConfigError(f"robots[{index}].domainId must be a number 0-232") from None
        robots.append(
            {
                "name": _text(item["name"]),
                "domain": domain,
                "namespace": _text(item.get("namespace")),
                "description": _text(item.get("description")),
                "enabled": item.get("enabled", True) is not False,
            }
        )
    for spec in filter(None, (s.strip() for s in os.environ.get("LIFECYCLE_ROBOTS", "").split(","))):
        parts = spec.split(":")
        if len(parts) not in (2, 3) or not parts[1].strip().isdigit():
            raise ConfigError(f"LIFECYCLE_ROBOTS entry {spec!r} must be NAME:DOMAIN or NAME:DOMAIN:/NAMESPACE")
        robots.append(
            {
                "name": parts[0].strip(),
                "domain": int(parts[1]),
                "namespace": parts[2].strip() if len(parts) == 3 else "",
                "description": "",
                "enabled": True,
            }
        )
    return robots


def cmd_env(role: str = "web") -> None:
    config = read_config()
    env = settings_env(config)
    robots_wanted(config)  # refuse a bad robot list now, in every container, with the reason
    for name, value in env.items():
        print(f"export {name}={shlex.quote(value)}")
    if CONFIG_FILE.is_file():
        log(f"read {CONFIG_FILE}" + (f" (sets {', '.join(sorted(env))})" if env else ""))
    if not os.environ.get("DJANGO_ALLOWED_HOSTS") and "DJANGO_ALLOWED_HOSTS" not in env:
        # Behind the Industrial Edge proxy the device's name is not known in advance. Only
        # the processes that serve HTTP need to say so (ingest and gateway serve none).
        if role not in ("ingest", "gateway"):
            log("WARNING: no allowed hosts configured (site.allowedHosts); accepting any Host and any "
                "WebSocket Origin. Set the device's host name to turn the origin check on.")
        print("export DJANGO_ALLOWED_HOSTS='*'")


def _django():
    import django

    os.environ.setdefault("DJANGO_SETTINGS_MODULE", "lifecycle_site.settings")
    app = os.environ.get("LIFECYCLE_APP_DIR", "/opt/lifecycle/app")
    if app not in sys.path:
        sys.path.insert(0, app)
    django.setup()


def ensure_admin(config: dict) -> None:
    from django.conf import settings
    from django.contrib.auth import get_user_model
    from django.contrib.auth.hashers import check_password, make_password
    from django.contrib.auth.models import Group
    from django.contrib.auth.password_validation import validate_password
    from django.core.exceptions import ValidationError

    admin = config.get("admin", {})
    username = _text(admin.get("username")) or os.environ.get("DJANGO_SUPERUSER_USERNAME") or "admin"
    password = admin.get("password") or os.environ.get("DJANGO_SUPERUSER_PASSWORD") or None
    email = _text(admin.get("email")) or os.environ.get("DJANGO_SUPERUSER_EMAIL", "")
    data = Path(settings.DATA_DIR)
    applied = data / ".admin-password-applied"  # hash of the configured password last applied
    users = get_user_model().objects
    user = users.filter(username=username).first()
    if password:
        try:
            validate_password(password)
        except ValidationError as exc:
            log(f"WARNING: the configured admin password is weak: {' '.join(exc.messages)}")
    if user is None:
        if not password:
            password = secrets.token_urlsafe(12)
            generated = data / "admin-password"
            generated.touch(mode=0o600)
            generated.write_text(password + "\n")
            log(f"no admin password configured: generated one, readable only inside the volume at {generated}")
        else:
            _write_private(applied, make_password(password))
        user = users.create_superuser(username, email, password)
        log(f"created the admin account {username!r}")
    elif password and not (applied.exists() and check_password(password, applied.read_text().strip())):
        user.set_password(password)
        user.is_active = True
        user.save()
        _write_private(applied, make_password(password))
        log(f"set the password of {username!r} from the configuration")
    group = Group.objects.filter(name="admin").first()
    if group is not None:
        user.groups.add(group)


def _write_private(path: Path, text: str) -> None:
    path.touch(mode=0o600)
    path.write_text(text + "\n")


def cmd_setup() -> None:
    config = read_config()
    robots = robots_wanted(config)
    _django()
    from django.core.management import call_command

    call_command("migrate", interactive=False, verbosity=1)
    ensure_admin(config)
    for robot in robots:
        call_command(
            "add_robot",
            robot["name"],
            domain=robot["domain"],
            namespace=robot["namespace"],
            description=robot["description"],
            disabled=not robot["enabled"],
            gateway=LOCAL_GATEWAY,
        )


def cmd_wait_for_schema(seconds: float) -> None:
    _django()
    from django.db import DatabaseError, connection
    from django.db.migrations.executor import MigrationExecutor

    deadline = time.monotonic() + seconds
    while True:
        try:
            executor = MigrationExecutor(connection)
            if not executor.migration_plan(executor.loader.graph.leaf_nodes()):
                return
            reason = "migrations are not applied yet"
        except DatabaseError as exc:
            reason = str(exc)
        connection.close()
        if time.monotonic() > deadline:
            raise ConfigError(
                f"the database schema is not ready after {seconds:g} s ({reason}); is the web container up?"
            )
        time.sleep(2)


def main(argv: list[str]) -> int:
    try:
        if argv[:1] == ["env"]:
            cmd_env(*argv[1:2])
        elif argv[:1] == ["setup"]:
            cmd_setup()
        elif argv[:1] == ["wait-for-schema"]:
            cmd_wait_for_schema(float(argv[1]) if len(argv) > 1 else 180)
        else:
            print(__doc__, file=sys.stderr)
            return 2
    except ConfigError as exc:
        log(f"ERROR: {exc}")
        return 78
    except Exception as exc:  # noqa: BLE001 - e.g. CommandError of add_robot: say it plainly
        from django.core.management.base import CommandError

        if isinstance(exc, CommandError):
            log(f"ERROR: {exc}")
            return 78
        raise
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
