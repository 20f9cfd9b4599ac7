"""A gateway's diagnostics facts (lifecycle_site/ingest/diagnostic_facts.py): statuses stored with
their level history and the times the alert rules need, the pages told, and a stranger's fact
checked field by field and bounded (statuses per fact, per robot, history per status)."""
from __future__ import annotations

import pytest

from lifecycle_site.diagnostics import models as dm
from lifecycle_site.diagnostics.models import Intake, LevelChange, Status, page_group
from lifecycle_site.fleet.models import Gateway, Robot
from lifecycle_site.ingest.facts import apply_facts
from ros_gateway.shared import protocol
from tests.gateway_part import GatewayPart

GATEWAY = "cell-d"
TOPIC = "/ud/diagnostics"


@pytest.fixture
def part(db) -> GatewayPart:
    Robot.objects.create(name="diag-unit", domain_id=41, namespace="/ud", gateway=Gateway.objects.create(name=GATEWAY))
    return GatewayPart(GATEWAY)


def entry(name: str, level: int = 0, **fields) -> dict:
    return {"name": name, "level": level, "message": fields.pop("message", "fine"), "hardware_id": "hw",
            "values": [["k", "v"]], "topic": TOPIC, "node": "/ud/driver", "stale": False, "age_s": 0.1, **fields}


def report(part: GatewayPart, *statuses: dict, heard=(), left_out: int = 0):
    fact = part.fact(protocol.DIAGNOSTICS, robot="diag-unit", statuses=list(statuses), heard=list(heard),
                     left_out=left_out)
    return apply_facts(GATEWAY, [fact])


def test_statuses_history_and_since_times_follow_the_reports(part):
    applied = report(part, entry("/R/Sensors/Lidar"), entry("driver: link", 1, message="slow"))
    robot_id = Robot.objects.get(name="diag-unit").id
    assert applied.pushes == [(page_group(robot_id), {"type": "diagnostics.changed",
                                                     "names": ["/R/Sensors/Lidar", "driver: link"], "more": False})]
    link = Status.objects.get(name="driver: link")
    assert (link.level, link.message, link.node, link.values) == (1, "slow", "/ud/driver", [["k", "v"]])
    assert link.warn_since is not None and link.error_since is None
    report(part, entry("driver: link", 2, message="lost"))
    report(part, entry("driver: link", 2, message="lost", stale=True, age_s=6.0))
    link.refresh_from_db()
    assert link.stale and link.word == "STALE" and link.stale_since and link.error_since is None
    report(part, entry("driver: link", 0))
    link.refresh_from_db()
    assert not link.stale and link.stale_since is None and link.warn_since is None
    assert list(LevelChange.objects.filter(name="driver: link").order_by("at", "id")
                .values_list("level", flat=True)) == [1, 2, 3, 0]
    # Heard again, unchanged: only its time moves; nothing is written to its history.
    report(part, heard=["driver: link"])
    assert LevelChange.objects.filter(name="driver: link").count() == 4


@pytest.mark.parametrize("bad", [
    {"level": 7}, {"level": "2"}, {"level": True}, {"name": ""}, {"name": "x" * (protocol.MAX_STATUS_NAME + 1)},
    {"values": [["k"]]}, {"values": [["k", 3]]}, {"values": [["k", "v"]] * (protocol.MAX_STATUS_VALUES + 1)},
    {"topic": "/other/diagnostics"}, {"topic": "/diagnostics"}, {"node": "not a node"}, {"age_s": -1},
    {"age_s": "nan"},
])
def test_a_strangers_status_is_refused_whole(part, bad):
    applied = report(part, entry("ok one"), {**entry("bad one"), **bad})
    assert applied.rejected == 1 and not Status.objects.exists()


def test_too_many_statuses_in_a_fact_or_names_heard_are_refused(part):
    statuses = [entry(f"s{i}") for i in range(protocol.MAX_STATUSES_PER_FACT + 1)]
    assert report(part, *statuses).rejected == 1
    assert report(part, heard=[1, 2]).rejected == 1
    fact = part.fact(protocol.DIAGNOSTICS, robot="someone-else", statuses=[], heard=[], left_out=0)
    assert apply_facts(GATEWAY, [fact]).rejected == 1


def test_text_is_cut_and_what_is_over_the_robots_bound_is_counted(part, monkeypatch):
    report(part, entry("long", message="m" * 5000))
    assert len(Status.objects.get(name="long").message) == protocol.MAX_STATUS_MESSAGE
    monkeypatch.setattr(protocol, "MAX_STATUSES", 3)
    report(part, entry("a"), entry("b"), entry("c"), left_out=9)
    assert Status.objects.count() == 3
    intake = Intake.objects.get()
    assert (intake.left_out_here, intake.left_out_by_gateway) == (1, 9)


def test_history_is_bounded_per_status(part, monkeypatch):
    monkeypatch.setattr(dm, "MAX_HISTORY", 5)
    monkeypatch.setattr("lifecycle_site.ingest.diagnostic_facts.MAX_HISTORY", 5)
    for index in range(12):
        report(part, entry("flapping", index % 2))
    levels = list(LevelChange.objects.filter(name="flapping").order_by("at", "id").values_list("level", flat=True))
    assert len(levels) == 5 and levels[-1] == 1


def test_statuses_their_gateway_no_longer_reports_are_marked_stale_by_the_site(part):
    from datetime import timedelta

    from django.utils import timezone

    from lifecycle_site.ingest.diagnostic_facts import mark_silent

    report(part, entry("quiet", 1, message="warm"), entry("chatty"))
    now = timezone.now()
    Status.objects.filter(name="quiet").update(heard=now - timedelta(seconds=30))
    pushes = mark_silent(now)
    quiet, chatty = Status.objects.get(name="quiet"), Status.objects.get(name="chatty")
    assert quiet.stale and quiet.stale_since == now and quiet.warn_since is None and not chatty.stale
    assert LevelChange.objects.filter(name="quiet").latest("at").level == dm.STALE
    assert pushes == [(page_group(quiet.robot_id), {"type": "diagnostics.changed", "names": ["quiet"], "more": False})]
    assert mark_silent(now) == []  # once
