"""``manage.py add_robot NAME --domain N [--namespace NS]``: register (or update) a robot."""
from __future__ import annotations

from django.core.exceptions import ValidationError
from django.core.management.base import BaseCommand, CommandError

from lifecycle_site.fleet.models import Robot


class Command(BaseCommand):
    help = "Register a robot (a ROS domain, optionally narrowed to a namespace) for the gateway to watch."

    def add_arguments(self, parser) -> None:
        parser.add_argument("name", help="Short name, e.g. agv-1")
        parser.add_argument("--domain", type=int, required=True, help="ROS_DOMAIN_ID of the robot (0-232)")
        parser.add_argument("--namespace", default="", help="Only nodes under this namespace, e.g. /agv1")
        parser.add_argument("--description", default="")
        parser.add_argument("--disabled", action="store_true", help="Register without watching it yet")

    def handle(self, *args, name: str, domain: int, namespace: str, description: str, disabled: bool, **options):
        robot = Robot.objects.filter(name=name).first() or Robot(name=name)
        created = robot.pk is None
        robot.domain_id, robot.namespace, robot.enabled = domain, namespace.rstrip("/"), not disabled
        if description:
            robot.description = description
        try:
            robot.full_clean()
        except ValidationError as exc:
            problems = "; ".join(f"{field}: {' '.join(msgs)}" for field, msgs in exc.message_dict.items())
            raise CommandError(problems) from None
        robot.save()
        verb = "Registered" if created else "Updated"
        where = f"ROS domain {domain}" + (f", namespace {robot.namespace}" if robot.namespace else "")
        self.stdout.write(self.style.SUCCESS(f"{verb} robot {name} ({where})."))
