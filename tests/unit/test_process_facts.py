"""A gateway's process facts (lifecycle_site/ingest/process_facts.py): one audit record each, the
profile's status following them, who asked only as far as the site vouches, and every field of a
stranger's fact checked."""
from __future__ import annotations

import pytest

from lifecycle_site.audit.models import ProcessRecord
from lifecycle_site.fleet.models import Gateway, ProcessProfile, Robot
from lifecycle_site.gateway_link.gateway_config import build_config
from lifecycle_site.ingest.facts import apply_facts
from ros_gateway.shared import protocol
from tests.conftest import make_user
from tests.gateway_part import GatewayPart

GATEWAY = "cell-p"


@pytest.fixture
def cell(db) -> tuple[GatewayPart, ProcessProfile]:
    robot = Robot.objects.create(name="proc-unit", domain_id=41, gateway=Gateway.objects.create(name=GATEWAY))
    profile = ProcessProfile.objects.create(robot=robot, name="drivers", command="/usr/bin/true", args=["-x"],
                                            env={"A": "1"}, secret_env={"TOKEN": "s3cret"})
    return GatewayPart(GATEWAY), profile


def process_fact(part: GatewayPart, action: str, outcome: str = "succeeded", **fields) -> dict:
    base = {"robot": "proc-unit", "process": "drivers", "action": action, "outcome": outcome, "source": "supervisor",
            "user_id": None, "pid": None, "old_pid": None, "exit_code": None, "exit_signal": None,
            "message": f"{action} {outcome}", "took_ms": 3.5}
    return part.fact(protocol.PROCESS, **{**base, **fields})


def test_each_fact_is_recorded_once_and_the_profile_follows(cell):
    part, profile = cell
    user = make_user("pia-operator", "operator")
    restart = part.vouch(process_fact(part, "restart", source="api", user_id=user.pk, pid=200, old_pid=100))
    first = apply_facts(GATEWAY, [restart, restart])
    assert len(first.created_processes) == 1 and apply_facts(GATEWAY, [restart]).created_processes == []
    record = ProcessRecord.objects.get()
    assert (record.action, record.outcome, record.source, record.requested_by, record.pid, record.old_pid) == (
        "restart", "succeeded", "api", user, 200, 100)
    profile.refresh_from_db()
    assert (profile.status, profile.pid, profile.restarts) == ("running", 200, 1)

    apply_facts(GATEWAY, [process_fact(part, "exited", "failed", old_pid=200, exit_signal="SIGKILL", exit_code=None)])
    profile.refresh_from_db()
    assert (profile.status, profile.pid, profile.last_exit_signal) == ("exited", None, "SIGKILL")
    apply_facts(GATEWAY, [process_fact(part, "respawn", pid=300, old_pid=200)])
    profile.refresh_from_db()
    assert (profile.status, profile.pid, profile.restarts) == ("running", 300, 2)


def test_a_late_report_does_not_overwrite_a_newer_status(cell):
    part, profile = cell
    late = process_fact(part, "respawn", pid=300)
    stopped = process_fact(part, "stop", source="config", old_pid=300)
    apply_facts(GATEWAY, [stopped])
    apply_facts(GATEWAY, [late])
    profile.refresh_from_db()
    assert (profile.status, profile.pid) == ("stopped", None)
    assert ProcessRecord.objects.count() == 2  # both on record all the same


def test_a_person_is_named_only_with_the_sites_grant(cell):
    part, _ = cell
    user = make_user("pia-operator", "operator")
    claimed = process_fact(part, "stop", source="dashboard", user_id=user.pk)  # no grant
    apply_facts(GATEWAY, [claimed])
    record = ProcessRecord.objects.get()
    assert (record.source, record.requested_by) == ("external", None)
    assert "the gateway said source dashboard, user #" in record.message


@pytest.mark.parametrize("change, why", [
    ({"process": "../etc"}, "process must be a launch profile's name"),
    ({"action": "reboot"}, "action"),
    ({"outcome": "maybe"}, "outcome"),
    ({"pid": -4}, "pid must be a process id"),
    ({"pid": True}, "pid must be a process id"),
    ({"exit_code": 10**9}, "exit_code"),
    ({"exit_signal": "kill -9"}, "exit_signal"),
    ({"took_ms": float("inf")}, "took_ms"),
    ({"robot": "someone-elses-robot"}, "not one of gateway"),
])
def test_a_malformed_fact_is_refused_and_the_others_still_apply(cell, change, why, caplog):
    part, _ = cell
    bad = {**process_fact(part, "start"), **change}
    good = process_fact(part, "start", pid=10)
    applied = apply_facts(GATEWAY, [bad, good])
    assert applied.rejected == 1 and ProcessRecord.objects.get().pid == 10
    assert why in caplog.text


def test_the_gateways_config_carries_enabled_profiles_with_their_secrets(cell):
    _, profile = cell
    (robot,) = build_config(GATEWAY)["robots"]
    (sent,) = robot["processes"]
    assert sent["name"] == "drivers" and sent["args"] == ["-x"] and sent["env"] == {"A": "1", "TOKEN": "s3cret"}
    assert "s3cret" not in str(profile.as_dict()) and "TOKEN" not in str(profile.as_dict())
    ProcessProfile.objects.filter(pk=profile.pk).update(enabled=False)
    assert build_config(GATEWAY)["robots"][0]["processes"] == []


def test_a_fact_about_a_removed_profile_is_still_recorded(cell):
    part, profile = cell
    profile.delete()
    apply_facts(GATEWAY, [process_fact(part, "stop", source="config", old_pid=5)])
    record = ProcessRecord.objects.get()
    assert (record.profile, record.process_name, record.message) == (None, "drivers", "stop succeeded")


def test_a_container_or_unit_fact_is_recorded_with_its_supervisor_and_leaves_profiles_alone(cell):
    part, profile = cell
    apply_facts(GATEWAY, [process_fact(part, "restart", process="docker:agv-sensors", supervisor="docker", pid=20,
                                       old_pid=10, exit_signal="SIGTERM"),
                          process_fact(part, "stop", process="systemd:agv-drivers.service", supervisor="systemd",
                                       old_pid=30, exit_code=0)])
    docker, systemd = ProcessRecord.objects.order_by("id")
    assert (docker.supervisor, docker.process_name, docker.profile, docker.exit_signal) == (
        "docker", "docker:agv-sensors", None, "SIGTERM")
    assert (systemd.supervisor, systemd.process_name, systemd.exit_code) == (
        "systemd", "systemd:agv-drivers.service", 0)
    profile.refresh_from_db()
    assert profile.restarts == 0 and profile.status != "running"


@pytest.mark.parametrize(("fields", "why"), [
    ({"process": "docker:agv-sensors", "supervisor": "launch"}, "is not one a launch supervisor has"),
    ({"process": "drivers", "supervisor": "docker"}, "is not one a docker supervisor has"),
    ({"process": "systemd:x.service", "supervisor": "docker"}, "is not one a docker supervisor has"),
    ({"process": "docker:a b", "supervisor": "docker"}, "process must be"),
    ({"process": "kubernetes:pod", "supervisor": "kubernetes"}, "process must be"),
    ({"process": "drivers", "supervisor": "kubernetes"}, "supervisor"),
])
def test_a_process_fact_whose_name_and_supervisor_do_not_agree_is_refused(cell, fields, why, caplog):
    part, _ = cell
    applied = apply_facts(GATEWAY, [process_fact(part, "start", **fields)])
    assert applied.rejected == 1 and not ProcessRecord.objects.exists()
    assert why in caplog.text
