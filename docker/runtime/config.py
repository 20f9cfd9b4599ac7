"""Apply the app configuration at container start (called by entrypoint.sh).

The configuration file ($LIFECYCLE_CONFIG_FILE, default /cfg-data/param.json) is what the
Industrial Edge Management writes from the JSON-Forms template (docker/edge/cfg-data-template):

    {
      "admin":  {"username": "admin", "password": "...", "email": ""},
      "site":   {"allowedHosts": "ied-1.plant.local", "csrfTrustedOrigins": "", "urlPrefix": "/lifecycle",
                 "behindTlsProxy": true, "timeZone": "Europe/Berlin", "logLevel": "INFO", "language": "de"},
      "ros":    {"discoveryRange": "SUBNET", "staticPeers": "", "discoveryServer": "", "superClient": true,
                 "serviceTimeout": 5},
      "robots": [{"name": "agv-1", "domainId": 21, "namespace": "", "description": "", "enabled": true}],
      "signIn": {"oidc": {"clientId": "lifecycle", "clientSecret": "...", "authorizationUrl": "https://...",
                          "tokenUrl": "https://...", "userinfoUrl": "https://...", "jwksUrl": "https://...",
                          "logoutUrl": "", "roles": {"operator": ["lifecycle-operators"], "admin": ["plant-it"]},
                          "groupsClaim": "groups", "buttonName": "", "caCertificate": ""},
                 "ldap": {"url": "ldaps://dir.plant:636", "caCertificate": "-----BEGIN CERTIFICATE-----...",
                          "userBase": "ou=people,dc=plant", "groupBase": "", "roles": "admin=plant-it",
                          "adDomain": "", "bindUser": "", "bindPassword": ""}}
    }

`site.language` (en, de) is LIFECYCLE_LANGUAGE; `signIn` sets the LIFECYCLE_OIDC_* and
LIFECYCLE_LDAP_* variables of docs/sign-in.md (roles as `role=group,group;role=group` or as an
object of role: [groups]); a caCertificate is written to /tmp and LIFECYCLE_*_CA_FILE names it.

A gateway of its own (docker/edge-cell: no site, it dials out to the central site's Redis)
takes its name and Redis from two more parts, which only the gateway role reads:

      "gateway": {"name": "cell-a", "channelPrefix": "lifecycle", "timeZone": "UTC", "logLevel": "INFO"},
      "redis":   {"url": "redis://site.plant.local:6379/0", "username": "gw-cell-a", "password": "...",
                  "caCertificate": "-----BEGIN CERTIFICATE-----..."}

`redis.url` may instead be the whole REDIS_URL that `manage.py add_gateway` printed (with the
gateway's user and password in it); `username`/`password`, when given, replace what the URL holds.

Every part is optional; an empty value leaves the environment's value in force.

    config.py env [ROLE]           print `export NAME='value'` lines for the settings (no Django);
                                   ROLE gateway also gets its name and Redis URL (gateway, redis)
    config.py setup                migrate, create/update the admin account, register the robots
                                   (all of the gateway "local", the one the site's compose runs)
    config.py wait-for-schema N    wait up to N seconds until the web container has migrated (ingest)
"""
from __future__ import annotations

import os
import secrets
import shlex
import sys
import time
from pathlib import Path

# The docstring above is the usage text (main prints it). The file is read, checked and turned
# into environment variables by config_env.py (no Django), found in this script's directory
# (sys.path[0]); this script prints them and does what needs Django. healthcheck.py imports this
# module and uses config.read_config and config.gateway_env.
from config_env import CONFIG_FILE, ConfigError, _text, gateway_env, read_config, robots_wanted, settings_env
from sign_in_env import sign_in_env

# The gateway the site's own compose file runs; robots of other gateways (cells) are added with
# `manage.py add_robot NAME --domain N --gateway CELL` or in the admin.
LOCAL_GATEWAY = "local"


def log(message: str) -> None:
    print(f"config: {message}", file=sys.stderr, flush=True)


def cmd_env(role: str = "web") -> None:
    config = read_config()
    env = settings_env(config)
    # The sign-in part is checked in every container (a bad one stops each with the reason), but
    # only web and manage sign people in: the client secret and the bind password stay with them,
    # and so do the CA files (each container has its own /tmp; the site's settings refuse an LDAP
    # CA file that is not there).
    signs_in = role not in ("ingest", "gateway")
    sign_in = sign_in_env(config, write_files=signs_in)
    if signs_in:
        env.update(sign_in)
    if role == "gateway":
        env.update(gateway_env(config, write_files=True))
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
