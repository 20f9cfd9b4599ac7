"""A robot's processes page without ROS (dashboard/process_views.py): what each launch profile's
row shows (never its environment), which buttons for whom, the polled part answering 204 while
nothing changed, and every refusal of a button answered plainly, on record where it was an
attempt."""
from __future__ import annotations

from datetime import timedelta

import pytest
from django.test import Client
from django.utils import timezone

from lifecycle_site.audit.models import ProcessRecord
from lifecycle_site.fleet.models import ProcessProfile, Robot
from lifecycle_site.gateway_link import gateways
from ros_gateway.shared import protocol
from tests import stack
from tests.conftest import client_of

ROBOT = "proc-page-agv"
PAGE = f"/robots/{ROBOT}/processes/"
ROWS = f"/robots/{ROBOT}/processes/rows"


def action_url(action: str, process: str = "drivers") -> str:
    return f"/robots/{ROBOT}/processes/{process}/{action}"


@pytest.fixture
def robot(db) -> Robot:
    return Robot.objects.create(name=ROBOT, domain_id=44)


@pytest.fixture
def drivers(robot) -> ProcessProfile:
    now = timezone.now()
    profile = ProcessProfile.objects.create(
        robot=robot, name="drivers", command="ros2", args=["launch", "agv_bringup", "drivers.launch.py"],
        env={"PLAIN_SETTING": "plain-env-value"}, secret_env={"DRIVER_TOKEN": "s3cret-env-value"})
    ProcessProfile.objects.filter(pk=profile.pk).update(
        status="running", pid=4242, status_since=now - timedelta(minutes=3, seconds=5), restarts=2,
        last_exit_code=None, last_exit_signal="SIGKILL", last_exit_at=now - timedelta(minutes=3, seconds=6),
        last_message="drivers on proc-page-agv started again as pid 4242.")
    ProcessRecord(profile=profile, robot_name=ROBOT, process_name="drivers", action="respawn", outcome="succeeded",
                  source="supervisor", pid=4242, message="drivers on proc-page-agv started again as pid 4242.",
                  at=now).save()
    profile.refresh_from_db()
    return profile


@pytest.fixture
def online(redis_server):
    """The gateway local's heartbeat, removed afterwards (other tests expect it never reported)."""
    stack.write_beat("local")
    yield
    stack.redis_client().delete(protocol.beat_key(gateways.channel_prefix(), "local"))
    gateways.forget()


def page_of(client: Client, url: str = PAGE) -> str:
    response = client.get(url)
    assert response.status_code == 200, response.status_code
    return response.content.decode()


def test_the_page_shows_each_process_status_and_never_its_environment(viewer_client, drivers):
    page = page_of(viewer_client)
    row = page.split(f'id="process-{drivers.pk}"')[1].split("</tr>")[0]
    assert "ros2 launch agv_bringup drivers.launch.py" in row
    assert ">running</span>" in row and ">4242<" in row
    assert f'data-elapsed-from="{drivers.status_since.isoformat()}">3 min</span>' in row  # uptime
    assert ">2<" in row  # restarts
    assert "SIGKILL, <time" in row and "3 min ago" in row  # the last exit: its signal and when
    assert "started again as pid 4242." in row
    # The newest records of the robot's processes.
    records = page.split('id="process-records"')[1].split("</tbody>")[0]
    assert "respawned" in records and "supervisor (by itself)" in records and "succeeded" in records
    for secret in ("plain-env-value", "s3cret-env-value", "DRIVER_TOKEN", "PLAIN_SETTING"):
        assert secret not in page
    assert "<button" not in row  # a viewer gets no buttons
    assert "hx-trigger=\"every 3s\"" in page and f'hx-get="{ROWS}"' in page


def test_an_operator_gets_the_buttons_that_fit_and_stop_asks_first(operator_client, drivers, online):
    row = page_of(operator_client).split(f'id="process-{drivers.pk}"')[1].split("</tr>")[0]
    assert ">Restart</button>" in row and ">Stop</button>" in row and ">Start</button>" not in row
    assert f'hx-post="{action_url("stop")}"' in row and " disabled " not in row
    assert f'data-confirm="Stop drivers on {ROBOT}?"' in row and 'data-confirm-yes="Stop"' in row
    assert "Its nodes stop with it. It stays stopped until someone starts it again" in row
    ProcessProfile.objects.filter(pk=drivers.pk).update(status="stopped", pid=None)
    row = page_of(operator_client).split(f'id="process-{drivers.pk}"')[1].split("</tr>")[0]
    assert ">Start</button>" in row and ">Restart</button>" not in row and ">Stop</button>" not in row
    assert ">stopped</span>" in row and "—" in row  # no pid, no uptime


def test_buttons_are_disabled_with_the_reason_while_the_gateway_is_offline(operator_client, drivers, redis_server):
    page = page_of(operator_client)
    assert "The gateway local is offline (it has never reported)" in page
    assert 'disabled title="The gateway local is offline: no command can be sent."' in page


def test_a_viewer_sees_no_buttons_and_may_not_act(viewer_client, drivers):
    assert "hx-post" not in page_of(viewer_client)
    refused = viewer_client.post(action_url("restart"))
    assert refused.status_code == 403 and b"operator needed" in refused.content
    assert not ProcessRecord.objects.exclude(source="supervisor").exists()


def test_unknown_robots_are_404(viewer_client, operator_client, db):
    assert viewer_client.get("/robots/no-such-robot/processes/").status_code == 404
    assert operator_client.post("/robots/no-such-robot/processes/drivers/stop").status_code == 404
    # The polled part of a page whose robot is gone reloads it (which then says so).
    gone = viewer_client.get("/robots/no-such-robot/processes/rows")
    assert (gone.status_code, gone["HX-Refresh"]) == (204, "true")


def test_an_action_with_the_gateway_offline_says_so_and_is_on_record(operator_client, drivers, redis_server):
    answer = operator_client.post(action_url("restart"), HTTP_HX_REQUEST="true")
    assert answer.status_code == 200  # a refusal a button meets: swapped by htmx, as the other pages do
    text = answer.content.decode()
    assert "Gateway offline:</strong> Gateway local is offline (" in text
    assert 'data-gateway-refusal="local"' in text
    assert 'id="processes-live" hx-swap-oob="innerHTML"' in text  # the rows and records along
    assert f'id="process-{drivers.pk}"' in text and "autofocus" in text
    record = ProcessRecord.objects.get(source="dashboard")
    assert (record.action, record.outcome, record.requested_by_name, record.profile_id) == (
        "restart", "rejected", "olga-operator", drivers.pk)
    assert record.message.startswith("Gateway local is offline (")
    assert record.message in text.split('id="process-records"')[1]  # in the records shown


def test_an_unknown_action_or_process_is_refused_plainly(operator_client, drivers):
    action = operator_client.post(action_url("reboot"))
    assert action.status_code == 400
    assert "No such action:</strong> &#x27;reboot&#x27; is not a process action; use one of start, stop, restart." \
        in action.content.decode()
    process = operator_client.post(action_url("stop", "sshd"))
    assert process.status_code == 404
    assert f"Robot {ROBOT} has no process &#x27;sshd&#x27; (its processes: drivers" in process.content.decode()
    assert not ProcessRecord.objects.filter(source="dashboard").exists()
    assert operator_client.get(action_url("stop")).status_code == 405  # POST only


def test_a_disabled_profile_is_refused_on_record(operator_client, drivers):
    ProcessProfile.objects.filter(pk=drivers.pk).update(enabled=False)
    answer = operator_client.post(action_url("start")).content.decode()
    assert "Disabled:</strong> The launch profile drivers of proc-page-agv is disabled; an admin enables it." in answer
    assert ProcessRecord.objects.get(source="dashboard").outcome == "rejected"


def test_the_polled_part_answers_204_until_something_changes(viewer_client, drivers, django_assert_max_num_queries):
    page = page_of(viewer_client)
    seen = page.split('<input type="hidden" name="seen" value="')[1].split('"')[0]
    with django_assert_max_num_queries(8):  # session, user, permissions, robot, profiles, records
        unchanged = viewer_client.get(ROWS, {"seen": seen})
    assert unchanged.status_code == 204 and not unchanged.content
    ProcessProfile.objects.filter(pk=drivers.pk).update(status="exited", pid=None, last_exit_code=1,
                                                        last_exit_signal="")
    changed = viewer_client.get(ROWS, {"seen": seen})
    assert changed.status_code == 200
    text = changed.content.decode()
    assert ">exited</span>" in text and "code 1, <time" in text
    assert "<html" not in text and f'value="{seen}"' not in text


def test_the_polled_part_reloads_a_page_whose_session_has_ended(drivers):
    answer = Client().get(ROWS)
    assert (answer.status_code, answer["HX-Refresh"]) == (204, "true")
    nobody = client_of("no-role-nora", None)
    assert nobody.get(ROWS)["HX-Refresh"] == "true"
    assert nobody.get(PAGE).status_code == 403


def test_a_robot_without_profiles_says_who_registers_them(viewer_client, robot):
    page = page_of(viewer_client)
    assert f"{ROBOT} has no launch profiles yet" in page and "An admin registers them in the admin (Launch profiles)" \
        in page
    assert "/admin/fleet/processprofile/add/" not in page
    admin = client_of("ada-processes-admin", "admin")
    assert f'href="/admin/fleet/processprofile/add/?robot={robot.pk}"' in page_of(admin)


def test_the_fleet_page_links_each_robot_to_its_processes(viewer_client, robot):
    assert f'href="{PAGE}">Processes</a>' in page_of(viewer_client, "/")


def test_a_container_running_nodes_is_a_row_with_its_nodes_and_a_hung_one_says_why(operator_client, drivers):
    from lifecycle_site.fleet.models import ManagedNode
    robot = drivers.robot
    now = timezone.now()
    ManagedNode.objects.create(robot=robot, name="/lidar", key=f"{ROBOT}.lidar", alive=True, state_id=13,
                               state_label="activating", state_changed=now - timedelta(seconds=95),
                               supervised_by="docker:agv-sensors")
    ManagedNode.objects.create(robot=robot, name="/camera", key=f"{ROBOT}.camera", alive=True, state_id=3,
                               state_label="active", supervised_by="docker:agv-sensors")
    ManagedNode.objects.create(robot=robot, name="/planner", key=f"{ROBOT}.planner", alive=True, state_id=3,
                               state_label="active", supervised_by="drivers")
    ProcessRecord(robot_name=ROBOT, process_name="docker:agv-sensors", supervisor="docker", action="restart",
                  outcome="succeeded", source="api", pid=5150, old_pid=5100, exit_signal="SIGKILL",
                  message="Container agv-sensors of proc-page-agv restarted as pid 5150.",
                  at=now - timedelta(minutes=2)).save()
    text = page_of(operator_client)
    row = text.split('id="process-unit-docker-agv-sensors"')[1].split("</tr>")[0]
    assert "Docker container" in row and "nodes: /camera, /lidar" in row
    assert "hung: /lidar stuck in activating for 95 s" in row
    assert ">5150<" in row and "SIGKILL" in row and 'data-transition="restart"' in row
    assert 'data-confirm-detail="Its nodes stop with it: /camera, /lidar.' in row
    profile_row = text.split(f'id="process-{drivers.pk}"')[1].split("</tr>")[0]
    assert "launch profile" in profile_row and "nodes: /planner" in profile_row and "hung" not in profile_row


def test_a_container_nobody_attributed_is_not_acted_on(operator_client, drivers):
    response = operator_client.post(action_url("stop", "docker:bystander"))
    assert response.status_code == 404
    assert "has no process &#x27;docker:bystander&#x27;" in response.content.decode()
    assert not ProcessRecord.objects.filter(process_name="docker:bystander").exists()


def test_cpu_and_memory_are_asked_of_the_gateway_and_checked(viewer_client, drivers, online, monkeypatch):
    """The usage poll: the gateway's answer (played here) checked, cells swapped into their rows."""
    from lifecycle_site.operations import processes as ops

    ops._usage_seen.clear()
    answers = []

    def gateway(name, command, timeout=None, **arguments):
        answers.append((name, command, arguments))
        return {"ok": True, "usage": {
            "drivers": {"cpu_percent": 12.5, "rss_bytes": 90 * 2**20, "processes": 3},
            "someone-elses": {"cpu_percent": 1.0, "rss_bytes": 1, "processes": 1},  # not the robot's: dropped
        }}

    monkeypatch.setattr(ops, "call_gateway", gateway)
    page = viewer_client.get(PAGE).content.decode()
    assert f'id="usage-{drivers.pk}"' in page and f'hx-get="/robots/{ROBOT}/processes/usage"' in page
    answer = viewer_client.get(f"/robots/{ROBOT}/processes/usage")
    text = answer.content.decode()
    assert answer.status_code == 200 and answers == [("local", "process_usage", {"robot": ROBOT})]
    assert f'<span id="usage-{drivers.pk}" class="usage" hx-swap-oob="true">12.5 % · 90 MB' in text
    assert "(3 processes)" in text and "someone-elses" not in text
    viewer_client.get(f"/robots/{ROBOT}/processes/usage")
    assert len(answers) == 1  # one measurement serves the pages open within 2 s

    for bad in ({"cpu_percent": -1, "rss_bytes": 1, "processes": 1}, {"cpu_percent": 1, "rss_bytes": "x"},
                {"cpu_percent": True, "rss_bytes": 1, "processes": 1}, "many"):
        assert ops._usage_value(bad) is None
