from django.apps import AppConfig


class RosGatewayConfig(AppConfig):
    """Registered so that ``manage.py ros_gateway`` exists; it defines no models."""

    name = "ros_gateway"
    verbose_name = "ROS gateway"
