"""``manage.py add_robot NAME --domain N [--namespace NS] [--gateway G]``: register (or update) a robot."""
from __future__ import annotations

from django.core.management.base import BaseCommand, CommandError
from django.utils.translation import gettext as _
from django.utils.translation import gettext_lazy, pgettext

from lifecycle_site.fleet.command_checks import clean_or_fail
from lifecycle_site.fleet.models import Gateway, Robot
from lifecycle_site.languages.cli import InCliLanguage
from ros_gateway.shared import protocol


class Command(InCliLanguage, BaseCommand):  # in the CLI's language: languages/cli.py
    help = gettext_lazy("Register a robot (a ROS domain, optionally narrowed to a namespace) for the gateway to watch.")

    def add_arguments(self, parser) -> None:
        parser.add_argument("name", help=_("Short name, e.g. agv-1"))
        parser.add_argument("--domain", type=int, required=True, help=_("ROS_DOMAIN_ID of the robot (0-232)"))
        parser.add_argument("--namespace", default="", help=_("Only nodes under this namespace, e.g. /agv1"))
        parser.add_argument("--gateway", default=protocol.DEFAULT_GATEWAY,
                            help=_("The gateway that reaches the robot (default %(gateway)s)") % {
                                "gateway": protocol.DEFAULT_GATEWAY})
        parser.add_argument("--description", default="")
        parser.add_argument("--disabled", action="store_true", help=_("Register without watching it yet"))

    def handle(self, *args, name: str, domain: int, namespace: str, gateway: str, description: str, disabled: bool,
               **options):
        found = Gateway.objects.filter(name=gateway).first()
        if found is None and gateway == protocol.DEFAULT_GATEWAY:
            # (stored: in English, like every description an admin did not write)
            found = Gateway.objects.create(name=gateway, description="The gateway on the site's own machine.")
        if found is None:
            known = ", ".join(Gateway.objects.values_list("name", flat=True)) or pgettext("list of gateways",
                                                                                        "none yet")
            raise CommandError(_("There is no gateway %(gateway)s (registered: %(known)s); add it first with "
                                 "manage.py add_gateway %(name)s.") % {
                "gateway": repr(gateway), "known": known, "name": gateway})
        robot = Robot.objects.filter(name=name).first() or Robot(name=name, gateway=found)
        created = robot.pk is None
        robot.gateway = found
        robot.domain_id, robot.namespace, robot.enabled = domain, namespace.rstrip("/"), not disabled
        if description:
            robot.description = description
        clean_or_fail(robot)
        robot.save()
        values = {"robot": name, "domain": domain, "namespace": robot.namespace, "gateway": found.name}
        if created and robot.namespace:
            done = _("Registered robot %(robot)s (ROS domain %(domain)s, namespace %(namespace)s, gateway "
                     "%(gateway)s).")
        elif created:
            done = _("Registered robot %(robot)s (ROS domain %(domain)s, gateway %(gateway)s).")
        elif robot.namespace:
            done = _("Updated robot %(robot)s (ROS domain %(domain)s, namespace %(namespace)s, gateway %(gateway)s).")
        else:
            done = _("Updated robot %(robot)s (ROS domain %(domain)s, gateway %(gateway)s).")
        self.stdout.write(self.style.SUCCESS(done % values))
