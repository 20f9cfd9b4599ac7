"""A gateway's settings are checked at start with an error that says what would do, and the
interfaces DDS may use become a Fast DDS profile (Jazzy has no variable for them)."""
from __future__ import annotations

import xml.etree.ElementTree as ET

import pytest

from ros_gateway.config import ANNOUNCEMENT_PERIOD_S, ConfigError, GatewayConfig, interfaces_profile
from ros_gateway.domain import FASTDDS_PROFILES

NS = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}


def load(**environ: str) -> GatewayConfig:
    return GatewayConfig.load("cell-a", environ)


@pytest.mark.parametrize("environ, says", [
    ({"ROS_AUTOMATIC_DISCOVERY_RANGE": "LAN"}, "use one of SYSTEM_DEFAULT, OFF, LOCALHOST, SUBNET"),
    ({"ROS_STATIC_PEERS": "10.0.0.5; bad peer"}, "is not a host name or address"),
    ({"ROS_DISCOVERY_SERVER": "10.0.0.1:port"}, "is not ADDRESS[:PORT]"),
    ({"ROS_SUPER_CLIENT": "yes"}, "use TRUE or FALSE"),
    ({"ROS_DISCOVERY_SERVER": "10.0.0.1:11811", "ROS_SUPER_CLIENT": "FALSE"}, "would see no robot's services"),
    ({"LIFECYCLE_DDS_INTERFACES": "no-such-if0"}, "this host has no network interface 'no-such-if0'"),
    ({"LIFECYCLE_DDS_INTERFACES": " , "}, "name at least one interface"),
    ({"LIFECYCLE_DDS_INTERFACES": "lo", "RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}, "with rmw_fastrtps_cpp only"),
    ({"LIFECYCLE_DDS_INTERFACES": "lo", "FASTRTPS_DEFAULT_PROFILES_FILE": "/etc/dds.xml"}, "not both"),
])
def test_unusable_dds_settings_are_refused_with_what_would_do(environ, says):
    with pytest.raises(ConfigError) as refused:
        load(**environ)
    assert says in str(refused.value)


@pytest.mark.parametrize("environ, says", [
    ({"LIFECYCLE_SERVICE_TIMEOUT": "5s"}, "LIFECYCLE_SERVICE_TIMEOUT='5s': expected a number of seconds, more than 0"),
    ({"LIFECYCLE_LIVENESS_INTERVAL": "-1"}, "LIFECYCLE_LIVENESS_INTERVAL='-1': expected a number of seconds, at"),
    ({"LIFECYCLE_LOG_BUFFER": "lots"}, "LIFECYCLE_LOG_BUFFER='lots': expected a whole number of log records"),
    ({"LIFECYCLE_HEARTBEAT_INTERVAL": "nan"}, "LIFECYCLE_HEARTBEAT_INTERVAL='nan': expected a number of seconds"),
])
def test_unusable_timings_name_the_variable_and_the_form_it_needs(environ, says):
    with pytest.raises(ConfigError) as refused:
        load(**environ)
    assert says in str(refused.value)


def test_the_gateway_reads_its_own_environment_not_the_sites_settings():
    config = load(REDIS_URL="redis://gw-cell-a:secret@10.0.0.9:6379/0", LIFECYCLE_CHANNEL_PREFIX="plant",
                  LIFECYCLE_SERVICE_TIMEOUT="2.5", LIFECYCLE_LOG_BUFFER="500")
    assert (config.redis_url, config.prefix) == ("redis://gw-cell-a:secret@10.0.0.9:6379/0", "plant")
    assert (config.service_timeout, config.log_buffer, config.heartbeat_interval) == (2.5, 500, 2.0)


def test_a_bad_gateway_name_is_refused():
    with pytest.raises(ConfigError, match="lower-case letters"):
        GatewayConfig.load("Cell A", {})


def test_interfaces_by_name_or_address_are_reported_as_addresses():
    config = load(LIFECYCLE_DDS_INTERFACES="lo, 10.1.2.3", ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET")
    assert config.dds == {"LIFECYCLE_DDS_INTERFACES": "127.0.0.1,10.1.2.3", "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}


def test_the_profile_lists_only_those_addresses_and_replaces_the_builtin_transports():
    root = ET.fromstring(interfaces_profile(["127.0.0.1", "10.1.2.3"]))
    assert [a.text for a in root.findall(".//f:interfaceWhiteList/f:address", NS)] == ["127.0.0.1", "10.1.2.3"]
    participant = root.find(".//f:participant", NS)
    assert participant.get("is_default_profile") == "true"
    assert participant.find(".//f:useBuiltinTransports", NS).text == "false"
    assert participant.find(".//f:userTransports/f:transport_id", NS).text == "lifecycle_udp"
    # It replaces fastdds_gateway.xml, so it keeps that file's memory and announcement settings too.
    for kind in ("data_writer", "data_reader"):
        assert root.find(f".//f:{kind}//f:allocated_samples", NS).text == "0"
    assert announcement_period(root) == announcement_period(ET.parse(FASTDDS_PROFILES).getroot())


def announcement_period(root: ET.Element) -> float:
    announcement = root.find(".//f:participant//f:discovery_config/f:leaseAnnouncement", NS)
    seconds = int(announcement.find("f:sec", NS).text) + int(announcement.find("f:nanosec", NS).text) / 1e9
    assert seconds == ANNOUNCEMENT_PERIOD_S
    return seconds


def test_a_discovery_server_makes_the_gateway_a_super_client_unless_told_otherwise():
    assert load(ROS_DISCOVERY_SERVER="10.0.0.1:11811").dds == {"ROS_DISCOVERY_SERVER": "10.0.0.1:11811",
                                                              "ROS_SUPER_CLIENT": "TRUE"}
