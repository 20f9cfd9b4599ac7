"""The lifecycle state machine facts both sides rely on."""
import pytest

from ros_gateway.shared import state_machine as sm


@pytest.mark.parametrize(
    "state, labels",
    [
        (sm.UNCONFIGURED, ["configure", "shutdown"]),
        (sm.INACTIVE, ["cleanup", "activate", "shutdown"]),
        (sm.ACTIVE, ["deactivate", "shutdown"]),
        (sm.FINALIZED, []),
        (sm.CONFIGURING, []),
        (sm.ERRORPROCESSING, []),
    ],
)
def test_only_valid_transitions_are_offered(state, labels):
    assert [t.label for t in sm.valid_transitions(state)] == labels


def test_shutdown_label_resolves_by_current_state_like_ros2_lifecycle_set():
    assert sm.resolve_transition("shutdown", sm.UNCONFIGURED).id == sm.UNCONFIGURED_SHUTDOWN
    assert sm.resolve_transition("shutdown", sm.INACTIVE).id == sm.INACTIVE_SHUTDOWN
    assert sm.resolve_transition("shutdown", sm.ACTIVE).id == sm.ACTIVE_SHUTDOWN


def test_numeric_ids_and_labels_resolve_alike():
    assert sm.resolve_transition(3, sm.INACTIVE) == sm.resolve_transition("activate", sm.INACTIVE)
    assert sm.resolve_transition("3", sm.INACTIVE).label == "activate"
    assert sm.resolve_transition(" Activate ", sm.INACTIVE).id == sm.ACTIVATE


def test_valid_name_in_wrong_state_is_none_not_an_error():
    assert sm.resolve_transition("activate", sm.UNCONFIGURED) is None
    assert sm.resolve_transition(1, sm.ACTIVE) is None


@pytest.mark.parametrize("bad", ["explode", 0, 10, 99, True, "on_configure_success"])
def test_unknown_or_internal_transitions_are_refused(bad):
    with pytest.raises(sm.UnknownTransition):
        sm.resolve_transition(bad, sm.UNCONFIGURED)


def test_every_external_transition_has_a_success_goal_and_an_edge():
    for transition in sm.EXTERNAL_TRANSITIONS:
        assert sm.SUCCESS_GOAL[transition.id] in sm.PRIMARY_STATES
        assert sm.transition_between(transition.start, transition.goal) == transition


def test_graph_covers_all_states_and_edges():
    graph = sm.transition_graph()
    assert len(graph) == len(sm.TRANSITIONS)
    reached = {edge["goal"]["id"] for edge in graph} | {edge["start"]["id"] for edge in graph}
    assert reached == set(sm.STATE_LABELS) - {sm.UNKNOWN}
