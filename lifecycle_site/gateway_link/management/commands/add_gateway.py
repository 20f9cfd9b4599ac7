"""``manage.py add_gateway NAME [--env-file PATH]``: register a gateway and give it Redis credentials.

Prints (or writes, mode 0600) the environment the gateway's process needs, one KEY=VALUE a
line. The password is shown this once: the site keeps only its SHA-256, from which the ingest
process re-creates the Redis user should Redis lose it. Running it again rotates the password
(the old one stops working at once, and connections made with it are closed).
"""
from __future__ import annotations

import os
import secrets
from pathlib import Path
from urllib.parse import urlsplit, urlunsplit

import redis
from django.conf import settings
from django.core.management.base import BaseCommand, CommandError
from django.utils.translation import gettext as _
from django.utils.translation import gettext_lazy

from lifecycle_site.fleet.command_checks import clean_or_fail
from lifecycle_site.fleet.models import Gateway
from lifecycle_site.gateway_link import gateways, quarantine, redis_users
from lifecycle_site.languages.cli import InCliLanguage


def gateway_url(base: str, user: str, password: str) -> str:
    """``base`` (the Redis the gateway reaches) with the gateway's own credentials."""
    parts = urlsplit(base)
    if not parts.hostname:
        raise CommandError(_("%(url)s is not a Redis URL such as redis://redis.plant:6379/0.") % {"url": repr(base)})
    host = f"[{parts.hostname}]" if ":" in parts.hostname else parts.hostname
    netloc = f"{user}:{password}@{host}" + (f":{parts.port}" if parts.port else "")
    return urlunsplit(parts._replace(netloc=netloc))


def write_private(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` readable by its owner only (also when the file existed)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.fchmod(fd, 0o600)
        os.write(fd, text.encode())
    finally:
        os.close(fd)


class Command(InCliLanguage, BaseCommand):  # in the CLI's language: languages/cli.py
    help = gettext_lazy("Register a gateway (or rotate its credentials) and print or write the environment its "
                        "process needs: its name and a Redis URL with a Redis user of its own.")

    def add_arguments(self, parser) -> None:
        parser.add_argument("name", help=_("Short name, e.g. cell-a (lower-case letters, digits, '-', '_')"))
        parser.add_argument("--env-file", type=Path, help=_("Write the environment to this file (mode 0600) instead "
                                                            "of printing it"))
        parser.add_argument("--description", default="", help=_("What the gateway reaches, e.g. 'assembly hall 2'"))
        parser.add_argument("--redis-url", default="", help=_("Redis as the gateway reaches it (default: this site's "
                                                              "REDIS_URL); any credentials in it are replaced by the "
                                                              "gateway's own"))

    def handle(self, *args, name: str, env_file: Path | None, description: str, redis_url: str, **options) -> None:
        gateway = Gateway.objects.filter(name=name).first() or Gateway(name=name)
        created = gateway.pk is None
        if description:
            gateway.description = description
        clean_or_fail(gateway)
        password = secrets.token_urlsafe(32)
        gateway.redis_password_sha256 = redis_users.password_sha256(password)
        url = gateway_url(redis_url or settings.REDIS_URL, gateway.redis_user, password)
        lines = [
            f"LIFECYCLE_GATEWAY_NAME={gateway.name}",
            f"REDIS_URL={url}",
            f"LIFECYCLE_CHANNEL_PREFIX={gateways.channel_prefix()}",
        ]
        if env_file is not None:
            try:
                write_private(env_file, "\n".join(lines) + "\n")
            except OSError as exc:
                raise CommandError(_("Cannot write %(file)s: %(error)s; nothing was changed.") % {
                    "file": env_file, "error": exc.strerror}) from None
        gateway.save()
        lifted = gateway.quarantined is not None
        try:
            if lifted:  # new credentials: the device may work again (gateway_link/quarantine.py)
                quarantine.lift(gateway)
            redis_users.apply_user(gateway)
            redis_users.disconnect_user(gateway.name)  # connections made with an old password
        except redis.RedisError as exc:
            self.stderr.write(self.style.WARNING(
                _("Redis at %(url)s did not take the user %(user)s (%(error)s). The ingest process creates it once "
                  "Redis answers; until then the gateway cannot connect.") % {
                    "url": gateways.safe_url(settings.REDIS_URL), "user": gateway.redis_user, "error": exc}
            ))
        values = {"gateway": gateway.name, "file": env_file}
        if env_file is not None:
            if created:
                done = _("Registered gateway %(gateway)s. Its environment is in %(file)s (readable by you only): "
                         "start its process with it, e.g. `env $(cat %(file)s) python -m ros_gateway`.")
            else:
                done = _("New credentials for gateway %(gateway)s. Its environment is in %(file)s (readable by you "
                         "only): start its process with it, e.g. `env $(cat %(file)s) python -m ros_gateway`.")
            self.stderr.write(self.style.SUCCESS(done % values))
        else:
            self.stdout.write("\n".join(lines))
            if created:
                done = _("Registered gateway %(gateway)s. The lines above are its process's environment; the "
                         "password is shown only now (run add_gateway again for a new one).")
            else:
                done = _("New credentials for gateway %(gateway)s. The lines above are its process's environment; "
                         "the password is shown only now (run add_gateway again for a new one).")
            self.stderr.write(self.style.SUCCESS(done % values))
        if not created:
            self.stderr.write(_("The previous password no longer works."))
        if lifted:
            self.stderr.write(_("Its quarantine is lifted: the site reads what it sends again."))
