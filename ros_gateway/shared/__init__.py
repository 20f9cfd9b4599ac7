"""The vocabulary the site and the gateways share: what crosses Redis between them
(protocol), the lifecycle state machine's facts, and ROS parameter types.

No rclpy and no Django here: the site imports only this package of ``ros_gateway``, and
nothing in ``ros_gateway`` imports the site, so the dependency runs one way.
"""
