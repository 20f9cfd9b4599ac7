"""``manage.py add_robot NAME --domain N [--namespace NS] [--gateway G]``: register (or update) a robot."""
from __future__ import annotations

from django.core.management.base import BaseCommand, CommandError

from lifecycle_site.fleet.command_checks import clean_or_fail
from lifecycle_site.fleet.models import Gateway, Robot
from ros_gateway.shared import protocol


class Command(BaseCommand):
    help = "Register a robot (a ROS domain, optionally narrowed to a namespace) for the gateway to watch."

    def add_arguments(self, parser) -> None:
        parser.add_argument("name", help="Short name, e.g. agv-1")
        parser.add_argument("--domain", type=int, required=True, help="ROS_DOMAIN_ID of the robot (0-232)")
        parser.add_argument("--namespace", default="", help="Only nodes under this namespace, e.g. /agv1")
        parser.add_argument("--gateway", default=protocol.DEFAULT_GATEWAY,
                            help=f"The gateway that reaches the robot (default {protocol.DEFAULT_GATEWAY})")
        parser.add_argument("--description", default="")
        parser.add_argument("--disabled", action="store_true", help="Register without watching it yet")

    def handle(self, *args, name: str, domain: int, namespace: str, gateway: str, description: str, disabled: bool,
               **options):
        found = Gateway.objects.filter(name=gateway).first()
        if found is None and gateway == protocol.DEFAULT_GATEWAY:
            found = Gateway.objects.create(name=gateway, description="The gateway on the site's own machine.")
        if found is None:
            known = ", ".join(Gateway.objects.values_list("name", flat=True)) or "none yet"
            raise CommandError(f"There is no gateway {gateway!r} (registered: {known}); add it first with "
                               f"manage.py add_gateway {gateway}.")
        robot = Robot.objects.filter(name=name).first() or Robot(name=name, gateway=found)
        created = robot.pk is None
        robot.gateway = found
        robot.domain_id, robot.namespace, robot.enabled = domain, namespace.rstrip("/"), not disabled
        if description:
            robot.description = description
        clean_or_fail(robot)
        robot.save()
        verb = "Registered" if created else "Updated"
        where = f"ROS domain {domain}" + (f", namespace {robot.namespace}" if robot.namespace else "")
        where += f", gateway {found.name}"
        self.stdout.write(self.style.SUCCESS(f"{verb} robot {name} ({where})."))
