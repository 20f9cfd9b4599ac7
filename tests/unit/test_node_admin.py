"""A node's admin page lists when it was away: the newest 20 absences of that node, read-only."""
from __future__ import annotations

from datetime import timedelta

from django.test import Client
from django.utils import timezone

from lifecycle_site.fleet.models import ManagedNode, NodeAbsence, Robot
from tests.conftest import make_user


def test_the_nodes_newest_absences_are_listed_read_only(db):
    robot = Robot.objects.create(name="admin-agv", domain_id=96)
    lidar = ManagedNode.objects.create(robot=robot, name="/lidar", first_seen=timezone.now())
    other = ManagedNode.objects.create(robot=robot, name="/camera", first_seen=timezone.now())
    now = timezone.now()
    for minutes in range(25):
        NodeAbsence.objects.create(node=lidar, gone_at=now - timedelta(minutes=minutes, seconds=30),
                                   back_at=now - timedelta(minutes=minutes), reason="unreachable")
    NodeAbsence.objects.create(node=other, gone_at=now, reason="process_lost")
    admin = make_user("ada-admin", "admin")
    client = Client()
    client.force_login(admin)
    page = client.get(f"/admin/fleet/managednode/{lidar.pk}/change/")
    assert page.status_code == 200
    text = page.content.decode()
    assert text.count('<td class="field-reason">') == 20 and "process lost" not in text
    assert 'name="absences-0-gone_at"' not in text  # read-only: no inputs
