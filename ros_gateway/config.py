"""A gateway's settings, all from its environment: its name, the site's Redis (with this
gateway's own credentials), timings, and the DDS discovery settings it runs with (reported
to the site and shown on the gateway's page). Checked at start, with a clear error."""
from __future__ import annotations

import atexit
import fcntl
import ipaddress
import os
import socket
import struct
import tempfile
from dataclasses import dataclass, field
from typing import Mapping
from xml.sax.saxutils import escape

from ros_gateway.shared import environment, protocol

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
# Ours: the network interfaces (names or IPv4 addresses, comma-separated) DDS may use; turned
# into a Fast DDS profile at start (Jazzy has no variable of its own for it).
INTERFACES_VARIABLE = "LIFECYCLE_DDS_INTERFACES"
FASTDDS_RMW = "rmw_fastrtps_cpp"


class ConfigError(ValueError):
    """A setting is unusable; the message names it and says what would do."""


@dataclass(frozen=True)
class GatewayConfig:
    name: str
    redis_url: str
    prefix: str
    # Their defaults are environment.agreed()'s, the site's too.
    service_timeout: float
    discovery_interval: float
    robot_refresh_interval: float
    heartbeat_interval: float
    log_buffer: int
    # One get_state per robot process this often (0: off), bounded by the timeout; two misses
    # in a row and its nodes are unreachable (see liveness.py).
    liveness_interval: float
    liveness_timeout: float
    dds: dict = field(default_factory=dict)
    # Supervisors of this host's containers and units that run nodes (host_units.py): the Docker
    # Engine's socket ("" off) and whether to use systemd's systemctl (where systemd runs the host).
    docker_socket: str = ""
    systemd: bool = False

    @property
    def lease_ttl(self) -> float:
        """A killed gateway's successor waits at most this long for its lease."""
        return max(3 * self.heartbeat_interval, 1.5)

    @classmethod
    def load(cls, name: str, environ: Mapping[str, str] = os.environ) -> "GatewayConfig":
        """From this gateway's environment (never the site's settings: a gateway has none of them)."""
        if not protocol.GATEWAY_NAME_RE.match(name):
            raise ConfigError(f"Gateway name {name!r}: use lower-case letters, digits, '-' and '_' (e.g. cell-a).")
        try:
            agreed = environment.agreed(environ)
            systemd = environment.flag("LIFECYCLE_SYSTEMD", True, environ)
        except environment.SettingError as exc:
            raise ConfigError(str(exc)) from None
        dds = {key: environ[key] for key in DDS_VARIABLES if environ.get(key)}
        check_dds(dds)
        if dds.get("ROS_DISCOVERY_SERVER") and "ROS_SUPER_CLIENT" not in dds:
            # A plain client of a discovery server learns only what it subscribes to: no
            # robot's services, so no lifecycle node. The gateway must see the whole graph.
            dds["ROS_SUPER_CLIENT"] = "TRUE"
        if environ.get(INTERFACES_VARIABLE, "").strip():
            dds[INTERFACES_VARIABLE] = ",".join(interface_addresses(environ[INTERFACES_VARIABLE], dds))
        return cls(
            name=name,
            redis_url=environment.text("REDIS_URL", protocol.DEFAULT_REDIS_URL, environ),
            prefix=environment.text("LIFECYCLE_CHANNEL_PREFIX", "lifecycle", environ),
            service_timeout=agreed["SERVICE_TIMEOUT"],
            discovery_interval=agreed["DISCOVERY_INTERVAL"],
            robot_refresh_interval=agreed["ROBOT_REFRESH_INTERVAL"],
            heartbeat_interval=agreed["HEARTBEAT_INTERVAL"],
            log_buffer=agreed["LOG_BUFFER"],
            liveness_interval=agreed["LIVENESS_INTERVAL"],
            liveness_timeout=agreed["LIVENESS_TIMEOUT"],
            dds=dds,
            docker_socket=environment.text("LIFECYCLE_DOCKER_SOCKET", "/var/run/docker.sock", environ),
            systemd=systemd,
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
    if dds.get("ROS_DISCOVERY_SERVER") and super_client is not None and super_client.upper() in ("FALSE", "0"):
        raise ConfigError("ROS_SUPER_CLIENT=FALSE with ROS_DISCOVERY_SERVER: the gateway would see no robot's "
                          "services (hence no lifecycle node); leave ROS_SUPER_CLIENT unset or set it TRUE.")


def _ipv4_of(interface: str) -> str | None:
    """The IPv4 address of a network interface of this host, None if it has none."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            packed = fcntl.ioctl(probe.fileno(), 0x8915, struct.pack("256s", interface[:15].encode()))  # SIOCGIFADDR
        except OSError:
            return None
    return socket.inet_ntoa(packed[20:24])


def interface_addresses(spec: str, dds: Mapping[str, str]) -> list[str]:
    """``eth1,10.0.0.5`` -> the IPv4 addresses DDS may use; a clear error for anything else."""
    if dds.get("RMW_IMPLEMENTATION", FASTDDS_RMW) != FASTDDS_RMW:
        raise ConfigError(f"{INTERFACES_VARIABLE} works with {FASTDDS_RMW} only, not {dds['RMW_IMPLEMENTATION']}.")
    if dds.get("FASTRTPS_DEFAULT_PROFILES_FILE"):
        raise ConfigError(f"Set either {INTERFACES_VARIABLE} or FASTRTPS_DEFAULT_PROFILES_FILE (put the interface "
                          "white list in your own profile), not both.")
    names = {name for _index, name in socket.if_nameindex()}
    addresses = []
    for item in filter(None, (part.strip() for part in spec.split(","))):
        try:
            addresses.append(str(ipaddress.IPv4Address(item)))
            continue
        except ValueError:
            pass
        if item not in names:
            raise ConfigError(f"{INTERFACES_VARIABLE}: this host has no network interface {item!r} "
                              f"(it has {', '.join(sorted(names))}).")
        address = _ipv4_of(item)
        if address is None:
            raise ConfigError(f"{INTERFACES_VARIABLE}: interface {item!r} has no IPv4 address (is it up?).")
        addresses.append(address)
    if not addresses:
        raise ConfigError(f"{INTERFACES_VARIABLE}: name at least one interface or IPv4 address.")
    return addresses


# How often the gateway's participant announces itself (fastdds_gateway.xml says why).
ANNOUNCEMENT_PERIOD_S = 1


def interfaces_profile(addresses: list[str]) -> str:
    """A Fast DDS profile whose participants use UDP on these addresses only; it also keeps the
    gateway's announcement period and its endpoints from pre-allocating samples, as
    ros_gateway/fastdds_gateway.xml does (it replaces that file)."""
    listed = "".join(f"<address>{escape(a)}</address>" for a in addresses)
    unallocated = "<topic><resourceLimitsQos><allocated_samples>0</allocated_samples></resourceLimitsQos></topic>"
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        '<dds xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"><profiles>\n'
        "  <transport_descriptors><transport_descriptor>\n"
        "    <transport_id>lifecycle_udp</transport_id><type>UDPv4</type>\n"
        f"    <interfaceWhiteList>{listed}</interfaceWhiteList>\n"
        "  </transport_descriptor></transport_descriptors>\n"
        '  <participant profile_name="lifecycle_gateway" is_default_profile="true"><rtps>\n'
        "    <builtin><discovery_config><leaseAnnouncement>"
        f"<sec>{ANNOUNCEMENT_PERIOD_S}</sec><nanosec>0</nanosec></leaseAnnouncement></discovery_config></builtin>\n"
        "    <userTransports><transport_id>lifecycle_udp</transport_id></userTransports>\n"
        "    <useBuiltinTransports>false</useBuiltinTransports>\n"
        "  </rtps></participant>\n"
        f'  <data_writer profile_name="lifecycle_gateway_writer" is_default_profile="true">'
        f"{unallocated}</data_writer>\n"
        f'  <data_reader profile_name="lifecycle_gateway_reader" is_default_profile="true">'
        f"{unallocated}</data_reader>\n"
        "</profiles></dds>\n"
    )


def apply_dds(config: GatewayConfig, environ=os.environ) -> None:
    """Before the first ROS participant: what the configuration adds to what ROS reads."""
    if config.dds.get("ROS_SUPER_CLIENT"):
        environ["ROS_SUPER_CLIENT"] = config.dds["ROS_SUPER_CLIENT"]
    spec = config.dds.get(INTERFACES_VARIABLE)
    if not spec:
        return
    handle, path = tempfile.mkstemp(prefix="lifecycle-gateway-dds-", suffix=".xml")
    with os.fdopen(handle, "w") as profile:
        profile.write(interfaces_profile(spec.split(",")))
    atexit.register(lambda: os.path.exists(path) and os.unlink(path))
    environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = path
