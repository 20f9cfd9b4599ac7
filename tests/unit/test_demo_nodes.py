"""The demo robot's periodic nodes (lidar, camera, planner, teleop) on real rclpy: they work on a
timer only while active, follow a change of their rate parameter at once, and release what
they own on deactivate, shutdown and error."""
from __future__ import annotations

import pytest
import rclpy
from rclpy.parameter import Parameter

from ros_gateway.demo.nodes import CameraDriver, JoyToVel, LidarDriver, Planner
from tests import stack

PERIODIC = [(LidarDriver, 10.0), (CameraDriver, 10.0), (Planner, 2.0), (JoyToVel, 20.0)]


@pytest.fixture
def context():
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=stack.domain(0))
    yield context
    rclpy.shutdown(context=context)


@pytest.mark.parametrize(("cls", "new_rate"), PERIODIC, ids=lambda v: getattr(v, "__name__", str(v)))
def test_a_periodic_node_ticks_only_while_active_at_its_rate(context, cls, new_rate):
    node = cls(f"unit_{cls.__name__.lower()}", context=context)
    try:
        assert node._timer is None
        node.trigger_configure()
        assert node.state_label == "inactive" and node._pub is not None and node._timer is None
        node.trigger_activate()
        assert node._timer is not None
        assert node._timer.timer_period_ns == pytest.approx(1e9 / node.param(cls.RATE_PARAMETER))
        node.set_parameters([Parameter(cls.RATE_PARAMETER, value=new_rate)])
        assert node._timer.timer_period_ns == pytest.approx(1e9 / new_rate)  # a new timer at the new rate
        node.trigger_deactivate()
        assert node.state_label == "inactive" and node._timer is None
        node.set_parameters([Parameter(cls.RATE_PARAMETER, value=new_rate / 2)])
        assert node._timer is None  # not started again while inactive
        node.trigger_activate()
        node.trigger_shutdown()
        assert node.state_label == "finalized" and node._pub is None and node._timer is None
        assert node._owned == []
    finally:
        node.destroy_node()
