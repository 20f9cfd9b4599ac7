"""The ROS side: a worker that owns all rclpy state. Importing this package loads no rclpy."""
