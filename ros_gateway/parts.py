"""What the parts of a gateway that talk to robots share, handed over as one object: the robots and
nodes known, the ROS domains, the facts going out, Redis, the bound on a call, and what this
host can tell of processes."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from ros_gateway.processes import LocalProcesses

if TYPE_CHECKING:  # the domain module loads rclpy
    from ros_gateway.domain import RosDomain
    from ros_gateway.outbox import Outbox
    from ros_gateway.registry import NodeRegistry
    from ros_gateway.relay import Relay


@dataclass
class Core:
    registry: NodeRegistry
    domains: dict[int, RosDomain]
    outbox: Outbox
    relay: Relay
    service_timeout: float
    processes: LocalProcesses = field(default_factory=LocalProcesses)
