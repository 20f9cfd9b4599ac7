"""A gateway's settings, all from its environment: its name, the site's Redis (with this
gateway's own credentials), timings, and the DDS discovery settings it runs with (reported
to the site and shown on the gateway's page). Checked at start, with a clear error."""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Mapping

from ros_gateway.shared import protocol

# DDS settings a gateway runs with, as any ROS 2 Jazzy process reads them.
DDS_VARIABLES = (
    "ROS_AUTOMATIC_DISCOVERY_RANGE",
    "ROS_STATIC_PEERS",
    "ROS_DISCOVERY_SERVER",
    "ROS_SUPER_CLIENT",
    "ROS_LOCALHOST_ONLY",
    "RMW_IMPLEMENTATION",
    "FASTRTPS_DEFAULT_PROFILES_FILE",
)
DISCOVERY_RANGES = ("SYSTEM_DEFAULT", "OFF", "LOCALHOST", "SUBNET")


class ConfigError(ValueError):
    """A setting is unusable; the message names it and says what would do."""


@dataclass(frozen=True)
class GatewayConfig:
    name: str
    redis_url: str
    prefix: str
    service_timeout: float = 5.0
    discovery_interval: float = 0.5
    robot_refresh_interval: float = 2.0
    heartbeat_interval: float = 2.0
    log_buffer: int = 20000
    # One get_state per robot process this often (0: off), bounded by the timeout; two misses
    # in a row and its nodes are unreachable (see liveness.py).
    liveness_interval: float = 1.0
    liveness_timeout: float = 1.5
    dds: dict = field(default_factory=dict)

    @property
    def lease_ttl(self) -> float:
        """A killed gateway's successor waits at most this long for its lease."""
        return max(3 * self.heartbeat_interval, 1.5)

    @classmethod
    def load(cls, name: str, settings, environ: Mapping[str, str] = os.environ) -> "GatewayConfig":
        """From Django's settings (which read the environment) and the DDS variables."""
        if not protocol.GATEWAY_NAME_RE.match(name):
            raise ConfigError(f"Gateway name {name!r}: use lower-case letters, digits, '-' and '_' (e.g. cell-a).")
        lifecycle = settings.LIFECYCLE
        dds = {key: environ[key] for key in DDS_VARIABLES if environ.get(key)}
        check_dds(dds)
        if lifecycle["LIVENESS_INTERVAL"] < 0 or lifecycle["LIVENESS_TIMEOUT"] <= 0:
            raise ConfigError("LIFECYCLE_LIVENESS_INTERVAL must be 0 (off) or more and LIFECYCLE_LIVENESS_TIMEOUT "
                              "more than 0 (seconds).")
        return cls(
            name=name,
            redis_url=settings.REDIS_URL,
            prefix=settings.CHANNEL_LAYERS["default"]["CONFIG"].get("prefix", "lifecycle"),
            service_timeout=lifecycle["SERVICE_TIMEOUT"],
            discovery_interval=lifecycle["DISCOVERY_INTERVAL"],
            robot_refresh_interval=lifecycle["ROBOT_REFRESH_INTERVAL"],
            heartbeat_interval=lifecycle["HEARTBEAT_INTERVAL"],
            log_buffer=lifecycle["LOG_BUFFER"],
            liveness_interval=lifecycle["LIVENESS_INTERVAL"],
            liveness_timeout=lifecycle["LIVENESS_TIMEOUT"],
            dds=dds,
        )


def check_dds(dds: Mapping[str, str]) -> None:
    """Refuse DDS settings that ROS would misread or ignore without a word."""
    value = dds.get("ROS_AUTOMATIC_DISCOVERY_RANGE")
    if value is not None and value.upper() not in DISCOVERY_RANGES:
        raise ConfigError(f"ROS_AUTOMATIC_DISCOVERY_RANGE={value!r}: use one of {', '.join(DISCOVERY_RANGES)}.")
    for peer in filter(None, (dds.get("ROS_STATIC_PEERS") or "").split(";")):
        if not peer.strip() or any(c.isspace() for c in peer.strip()):
            raise ConfigError(f"ROS_STATIC_PEERS: {peer!r} is not a host name or address (separate peers with ';').")
    for server in filter(None, (dds.get("ROS_DISCOVERY_SERVER") or "").split(";")):
        host, _, port = server.strip().rpartition(":")
        if server.strip() and (not host and not port or port and not port.isdigit()):
            raise ConfigError(f"ROS_DISCOVERY_SERVER: {server!r} is not ADDRESS[:PORT] (separate servers with ';').")
    super_client = dds.get("ROS_SUPER_CLIENT")
    if super_client is not None and super_client.upper() not in ("TRUE", "FALSE", "1", "0"):
        raise ConfigError(f"ROS_SUPER_CLIENT={super_client!r}: use TRUE or FALSE.")
