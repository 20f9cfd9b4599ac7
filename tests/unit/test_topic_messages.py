"""Pairing transition events, and mapping /rosout loggers to nodes (no ROS needed)."""
from ros_gateway.shared import state_machine as sm
from ros_gateway.topic_messages import LogBuffer, TransitionTracker, owning_node


def test_external_transition_is_reported_once_with_its_outcome():
    tracker = TransitionTracker()
    # rclpy publishes id 0 in the event's transition field; the edge tells which one it is.
    assert tracker.observe(sm.INACTIVE, sm.ACTIVATING, 0) == (None, True)
    done, _ = tracker.observe(sm.ACTIVATING, sm.ACTIVE, 0)
    assert (done.transition.label, done.start_state, done.result_state, done.outcome) == (
        "activate", sm.INACTIVE, sm.ACTIVE, "succeeded")


def test_error_path_is_one_failed_transition():
    tracker = TransitionTracker()
    tracker.observe(sm.INACTIVE, sm.ACTIVATING, 0)
    assert tracker.observe(sm.ACTIVATING, sm.ERRORPROCESSING, 0)[0] is None
    done, _ = tracker.observe(sm.ERRORPROCESSING, sm.UNCONFIGURED, 0)
    assert done.outcome == "failed" and done.result_state == sm.UNCONFIGURED


def test_transitions_the_gateway_sent_are_not_reported_as_external():
    tracker = TransitionTracker(commanded=sm.CONFIGURE)
    tracker.observe(sm.UNCONFIGURED, sm.CONFIGURING, 0)
    assert tracker.observe(sm.CONFIGURING, sm.INACTIVE, 0) == (None, True)
    # ... but the next one, by someone else, is.
    tracker.observe(sm.INACTIVE, sm.ACTIVATING, 0)
    assert tracker.observe(sm.ACTIVATING, sm.ACTIVE, 0)[0].outcome == "succeeded"


def test_a_transition_of_others_after_ours_ended_overtakes_it_and_one_before_does_not():
    tracker = TransitionTracker()
    tracker.observe(sm.UNCONFIGURED, sm.CONFIGURING, 0)  # another tool's configure, before our request
    tracker.observe(sm.CONFIGURING, sm.INACTIVE, 0)
    tracker.commanded = sm.ACTIVATE  # ours
    tracker.observe(sm.INACTIVE, sm.ACTIVATING, 0)
    tracker.observe(sm.ACTIVATING, sm.ACTIVE, 0)
    assert not tracker.overtaken(sm.ACTIVATE)  # what came before it does not count
    tracker.observe(sm.ACTIVE, sm.DEACTIVATING, 0)  # another tool's deactivate, after it
    tracker.observe(sm.DEACTIVATING, sm.INACTIVE, 0)
    assert tracker.overtaken(sm.ACTIVATE) and not tracker.overtaken(sm.CONFIGURE)
    tracker.observe(sm.CONFIGURING, sm.INACTIVE, 0)  # only the end of one seen counts too
    assert tracker.foreign_since_ended == 2


def test_the_late_beginning_of_one_request_leaves_the_next_one_ours():
    """A group run: configure's reply came before its beginning, and the step's activate is
    claimed when configure's beginning arrives. The activate stays ours (not 'external')."""
    tracker = TransitionTracker(settled=sm.CONFIGURE, commanded=sm.ACTIVATE)
    assert tracker.observe(sm.UNCONFIGURED, sm.CONFIGURING, 0) == (None, False)
    assert tracker.observe(sm.CONFIGURING, sm.INACTIVE, 0) == (None, True)
    assert tracker.observe(sm.INACTIVE, sm.ACTIVATING, 0) == (None, True)
    assert tracker.observe(sm.ACTIVATING, sm.ACTIVE, 0) == (None, True)  # no external record
    assert tracker.ended_as(sm.ACTIVATE) == sm.ACTIVE


def test_the_end_of_our_request_is_kept_for_its_answer_that_may_be_lost():
    tracker = TransitionTracker(commanded=sm.ACTIVATE)
    tracker.observe(sm.INACTIVE, sm.ACTIVATING, 0)
    assert tracker.ended_as(sm.ACTIVATE) is None  # under way
    tracker.observe(sm.ACTIVATING, sm.ERRORPROCESSING, 0)
    assert tracker.ended_as(sm.ACTIVATE) is None  # still under way
    tracker.observe(sm.ERRORPROCESSING, sm.UNCONFIGURED, 0)
    assert tracker.ended_as(sm.ACTIVATE) == sm.UNCONFIGURED and tracker.ended_as(sm.CONFIGURE) is None
    tracker.ended = None
    tracker.observe(sm.UNCONFIGURED, sm.CONFIGURING, 0)  # another tool's: not ours
    tracker.observe(sm.CONFIGURING, sm.INACTIVE, 0)
    assert tracker.ended is None


def test_missed_beginning_is_recorded_as_observed():
    done, news = TransitionTracker().observe(sm.CONFIGURING, sm.INACTIVE, 0)
    assert done.outcome == "observed" and done.transition is None and news


def test_late_beginning_of_our_own_request_does_not_roll_the_state_back():
    # The reply said "active" already; the event "inactive -> activating" arrives after it.
    tracker = TransitionTracker(settled=sm.ACTIVATE)
    assert tracker.observe(sm.INACTIVE, sm.ACTIVATING, 0) == (None, False)
    assert tracker.observe(sm.ACTIVATING, sm.ACTIVE, 0) == (None, True)


def test_loggers_map_to_nodes_including_namespaces_and_child_loggers():
    nodes = {"/joy_to_vel", "/agv1/lidar_driver"}
    assert owning_node("joy_to_vel", nodes) == "/joy_to_vel"
    assert owning_node("agv1.lidar_driver", nodes) == "/agv1/lidar_driver"
    assert owning_node("agv1.lidar_driver.decoder", nodes) == "/agv1/lidar_driver"
    assert owning_node("joystick", nodes) is None


def test_log_buffer_is_bounded_and_counts_what_it_drops():
    buffer = LogBuffer(limit=3)
    for i in range(5):
        buffer.append(i)
    assert len(buffer) == 3 and buffer.dropped == 2 and buffer.received == 5
    assert buffer.drain(10) == [2, 3, 4]  # the newest survive
