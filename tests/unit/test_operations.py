"""The operations table (ros_gateway/shared/operations.py) and what reads it: an operation
declared there is offered by the page, the API, the CLI and the docs."""
from __future__ import annotations

from pathlib import Path

import pytest
from django.test import Client

from lifecycle_site.fleet.models import GroupRun, Robot
from lifecycle_site.operations import cli_output
from lifecycle_site.operations.runs import start_run
from lifecycle_site.refusal import Refusal
from ros_gateway.shared import operations
from ros_gateway.shared import state_machine as sm
from tests.conftest import make_user

ROOT = Path(__file__).resolve().parents[2]


def test_docs_operations_md_is_written_from_the_table():
    written = (ROOT / "docs" / "operations.md").read_text()
    assert written == operations.markdown(), "run: python -m ros_gateway.shared.operations > docs/operations.md"


def test_every_phase_can_be_reached_from_every_primary_state_but_finalized():
    for op in operations.OPERATIONS:
        for phase in op.phases:
            if phase.target == operations.EACH_NODES_OWN:
                continue  # a mode's targets: see tests/unit/test_mode_plan.py
            for state in (sm.UNCONFIGURED, sm.INACTIVE, sm.ACTIVE):
                assert state in phase.leave_alone or sm.path(state, phase.target) is not None, (op.name, state)


def test_names_and_buttons_are_unique_and_fit_the_run_model():
    assert len(operations.BY_NAME) == len(operations.OPERATIONS)
    assert len({op.button for op in operations.OPERATIONS}) == len(operations.OPERATIONS)
    longest = GroupRun._meta.get_field("operation").max_length
    assert all(len(op.name) <= longest for op in operations.OPERATIONS)
    assert dict(GroupRun._meta.get_field("operation").choices) == dict(operations.choices())


def test_only_the_gateway_starts_a_recovery():
    assert "recover" not in operations.names()
    assert operations.names(operations.NODE) == ["restart"]
    assert "restart_all" in operations.names(operations.ROBOT)


def test_the_cli_has_a_verb_for_every_startable_operation():
    for name in operations.names():
        assert name in cli_output.VERBS and name in cli_output.RUN_VERBS
    assert "recover" not in cli_output.VERBS


@pytest.mark.django_db
def test_the_fleet_page_has_a_button_per_robot_operation_with_its_question(operator_client: Client):
    Robot.objects.create(name="table-agv", domain_id=97)
    page = operator_client.get("/").content.decode()
    for op in operations.OPERATIONS:
        button = f'name="operation" value="{op.name}"'
        assert (button in page) == (op.scope == operations.ROBOT), op.name
        if op.confirm and op.scope == operations.ROBOT:
            assert op.confirm_text("table-agv") in page


@pytest.mark.django_db
def test_the_api_names_every_robot_operation_when_one_is_unknown(operator_client: Client):
    Robot.objects.create(name="table-agv", domain_id=97)
    response = operator_client.post("/api/v1/robots/table-agv/operations", {"operation": "explode"},
                                    content_type="application/json")
    assert response.status_code == 400
    message = response.json()["error"]["message"]
    assert all(name in message for name in operations.names(operations.ROBOT))
    assert "recover" not in message


@pytest.mark.django_db
def test_an_operation_is_started_only_by_a_user_with_its_role():
    robot = Robot.objects.create(name="table-agv", domain_id=97)
    for op in operations.OPERATIONS:
        if op.startable:
            with pytest.raises(Refusal) as refused:
                start_run(robot, op.name, user=make_user("victor-viewer", "viewer"), source="cli",
                          nodes=["/x"] if op.scope == operations.NODE else None)
            assert (refused.value.code, refused.value.status) == ("forbidden", 403)
            assert refused.value.message == f"{op.button} needs the {op.role} role."
    assert not GroupRun.objects.exists()
