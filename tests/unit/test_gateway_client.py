"""The site's side of a gateway command (lifecycle_site/gateway_link/gateway_client.py) on the real Redis,
the gateway's part played by the test as the wire contract says: what is sent, a reply taken
(and one the site cannot read refused in words), a refusal's code kept, a gateway offline or
silent answered without waiting for nothing, and a command nobody took withdrawn, on record as
not carried out."""
from __future__ import annotations

import json
import threading

import pytest

from lifecycle_site.gateway_link import gateways
from lifecycle_site.gateway_link.gateway_client import (
    MAX_SERVICE_TIMEOUT,
    GatewayError,
    GatewayOffline,
    _service_timeout,
    call_gateway,
)
from ros_gateway.shared import protocol
from tests import stack

GATEWAY = "gc-cell"


@pytest.fixture
def online(redis_server):
    """The gateway's heartbeat, and its queue and keys removed afterwards."""
    stack.write_beat(GATEWAY)
    yield stack.redis_client()
    client = stack.redis_client()
    for key in client.keys(f"{gateways.channel_prefix()}*{GATEWAY}*"):
        client.delete(key)
    gateways.forget()


def answer_once(client, reply: bytes | None) -> tuple[threading.Thread, list[dict]]:
    """Take the next command from the gateway's queue (as the gateway does) and answer ``reply``."""
    taken: list[dict] = []
    queue = protocol.command_queue(gateways.channel_prefix(), GATEWAY)

    def serve() -> None:
        popped = client.brpop([queue], timeout=10)
        if popped is None:
            return
        command = json.loads(popped[1])
        taken.append(command)
        if reply is not None:
            client.lpush(protocol.reply_key(gateways.channel_prefix(), GATEWAY, command["request_id"]), reply)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    return thread, taken


def test_a_command_goes_out_with_its_bounds_and_the_reply_comes_back(online):
    answer = {"ok": True, "state": {"id": 3}, "facts": [{"id": "f1"}]}
    thread, taken = answer_once(online, json.dumps(answer).encode())
    reply = call_gateway(GATEWAY, protocol.CHANGE_STATE, timeout=2.5, robot="agv-1", node="/lidar",
                         transition="activate")
    thread.join(5)
    assert reply["ok"] is True and reply["facts"] == [{"id": "f1"}]
    (command,) = taken
    assert (command["command"], command["robot"], command["node"], command["timeout"]) == (
        protocol.CHANGE_STATE, "agv-1", "/lidar", 2.5)
    assert command["deadline"] > 0 and len(command["request_id"]) == 32 and command["requested_at"]


@pytest.mark.parametrize("raw", [b"not json", b"[1, 2]", b"{" * 100_000, b'"ok"'])
def test_a_reply_the_site_cannot_read_is_refused_in_words(online, raw):
    thread, _ = answer_once(online, raw)
    with pytest.raises(GatewayError) as refused:
        call_gateway(GATEWAY, protocol.CHANGE_STATE, timeout=1, robot="agv-1")
    thread.join(5)
    assert refused.value.code == "gateway_error" and refused.value.carried_out is None
    assert "answered with something the site cannot read" in refused.value.message


def test_a_refusal_keeps_its_code_and_message_and_nothing_reached_the_node(online):
    reply = {"ok": False, "error": {"code": "invalid_transition", "message": "Cannot activate from unconfigured."},
             "facts": [{"id": "r1"}]}
    thread, _ = answer_once(online, json.dumps(reply).encode())
    with pytest.raises(GatewayError) as refused:
        call_gateway(GATEWAY, protocol.CHANGE_STATE, timeout=1, robot="agv-1")
    thread.join(5)
    assert (refused.value.code, refused.value.message, refused.value.carried_out) == (
        "invalid_transition", "Cannot activate from unconfigured.", False)
    assert refused.value.facts == [{"id": "r1"}]


def test_an_offline_gateway_is_refused_before_anything_is_sent(redis_server):
    stack.write_beat(GATEWAY, at=0.0)  # its last beat long ago
    try:
        with pytest.raises(GatewayOffline) as refused:
            call_gateway(GATEWAY, protocol.CHANGE_STATE, timeout=1, robot="agv-1")
        assert "agv-1" in refused.value.message
        assert stack.redis_client().llen(protocol.command_queue(gateways.channel_prefix(), GATEWAY)) == 0
    finally:
        stack.redis_client().delete(protocol.beat_key(gateways.channel_prefix(), GATEWAY))
        gateways.forget()


def test_a_command_nobody_took_is_withdrawn_and_said_not_carried_out(online, settings):
    settings.LIFECYCLE = {**settings.LIFECYCLE, "COMMAND_GRACE": 0.2}
    with pytest.raises(GatewayOffline) as withdrawn:
        call_gateway(GATEWAY, protocol.CHANGE_STATE, timeout=0.1, robot="agv-1", node="/lidar")
    assert withdrawn.value.details["carried_out"] is False
    assert "so the command was withdrawn: it was not carried out, nothing was sent to agv-1" in withdrawn.value.message
    assert online.llen(protocol.command_queue(gateways.channel_prefix(), GATEWAY)) == 0  # taken back
    (fact,) = withdrawn.value.facts  # the record of what was not done
    assert fact["outcome"] == "rejected" and fact["robot"] == "agv-1"


@pytest.mark.parametrize(("asked", "expected"), [
    (None, 5.0), (0.0, 0.1), (2.5, 2.5), (1e9, MAX_SERVICE_TIMEOUT), (float("inf"), 5.0), (float("nan"), 5.0),
    (10**400, MAX_SERVICE_TIMEOUT)])
def test_the_service_timeout_is_bounded(asked, expected, settings):
    settings.LIFECYCLE = {**settings.LIFECYCLE, "SERVICE_TIMEOUT": 5.0}
    assert _service_timeout(asked) == expected
