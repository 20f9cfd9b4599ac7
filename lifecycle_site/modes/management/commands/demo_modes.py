"""``manage.py demo_modes ROBOT ...``: the demo robots' modes (``make demo``): a template for both,
"mapping" (the lidar fast, the camera and planner off) and "production" (everything active, the
planner replanning faster, ready while /scan comes at >= 4 Hz). Left as they are if they exist."""
from __future__ import annotations

from django.core.management.base import BaseCommand

from lifecycle_site.fleet.models import Robot
from lifecycle_site.modes.models import Mode

DEMO_MODES = {
    "mapping": ("Building the map: the lidar scans fast, the camera and the planner rest.", {
        "/lidar_driver": {"state": "active", "parameters": {"scan_rate_hz": 12.0}},
        "/camera_driver": {"state": "inactive"},
        "/planner": {"state": "unconfigured"},
        "/joy_to_vel": {"state": "active"},
    }, [{"node": "/lidar_driver", "state": "active"}, {"topic": "/scan", "min_hz": 10, "window_s": 3}]),
    "production": ("Driving jobs: every node active, the planner replanning at 2 Hz.", {
        "/lidar_driver": {"state": "active", "parameters": {"scan_rate_hz": 5.0}},
        "/camera_driver": {"state": "active"},
        "/planner": {"state": "active", "parameters": {"planner_frequency_hz": 2.0}},
        "/joy_to_vel": {"state": "active"},
    }, [{"node": "/planner", "state": "active"}, {"topic": "/scan", "min_hz": 4, "window_s": 3}]),
}


class Command(BaseCommand):
    help = __doc__

    def add_arguments(self, parser) -> None:
        parser.add_argument("robots", nargs="+", metavar="ROBOT")

    def handle(self, *args, robots: list[str], **options) -> None:
        found = list(Robot.objects.filter(name__in=robots))
        for name, (description, nodes, ready) in DEMO_MODES.items():
            mode, _ = Mode.objects.get_or_create(name=name, defaults={
                "description": description, "nodes": nodes, "ready_when": ready})
            mode.robots.add(*found)
