"""The site's shortcuts on hot paths keep their promises: what a token grants is kept a few
seconds but a revoked token, a deactivated user or a lost role stop working at once; a
gateway's heartbeat is re-read from Redis every second; fleet rows get their links without a reverse()
per node and the fleet snapshot of a WebSocket is read and rendered off the event loop."""
import json
import threading
import time
from datetime import timedelta

import pytest
from asgiref.sync import async_to_sync
from channels.layers import get_channel_layer
from channels.routing import URLRouter
from channels.testing import WebsocketCommunicator
from django.contrib.auth.models import Group, Permission
from django.db import connection
from django.template.loader import render_to_string
from django.test import Client, override_settings
from django.test.utils import CaptureQueriesContext
from django.urls import reverse
from django.utils import timezone

from lifecycle_site.api import grants
from lifecycle_site.api.models import ApiToken, hash_token
from lifecycle_site.dashboard import consumers, snapshots
from lifecycle_site.fleet.models import Gateway, ManagedNode, Robot
from lifecycle_site.gateway_link import gateway_client, gateways
from lifecycle_site.prefix import script_prefix
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm
from tests import stack
from tests.conftest import make_user, session_of
from tests.unit.sockets import receive_until

AUTH_TABLES = ("api_apitoken", "auth_user", "auth_permission", "auth_group")


def token_client(user) -> tuple[Client, ApiToken]:
    record, token = ApiToken.issue(user)
    return Client(headers={"Authorization": f"Bearer {token}"}), record


def transition(client: Client, node: ManagedNode):
    return client.post(f"/api/v1/nodes/{node.key}/transition", json.dumps({"transition": "configure"}),
                       content_type="application/json")


@pytest.fixture
def node(db) -> ManagedNode:
    robot = Robot.objects.create(name="cache-agv", domain_id=97)
    return ManagedNode.objects.create(robot=robot, name="/joy_to_vel", alive=True, state_id=sm.UNCONFIGURED,
                                      state_label="unconfigured")


# --- what a token grants ---------------------------------------------------------------------

def test_a_kept_grant_spares_the_token_user_and_permission_queries(db):
    client, record = token_client(make_user("tess-token", "viewer"))
    with CaptureQueriesContext(connection) as first:
        assert client.get("/api/v1/robots").status_code == 200
    with CaptureQueriesContext(connection) as second:
        assert client.get("/api/v1/robots").status_code == 200
    sql_first = " ".join(q["sql"] for q in first.captured_queries)
    sql_second = " ".join(q["sql"] for q in second.captured_queries)
    assert "api_apitoken" in sql_first and "auth_permission" in sql_first
    assert not any(table in sql_second for table in AUTH_TABLES), sql_second
    record.refresh_from_db()
    assert record.last_used is not None  # written by the first request only


def test_the_user_of_a_kept_grant_is_a_fresh_full_object(node):
    user = make_user("olga-token", "operator")
    client, _ = token_client(user)
    for _ in range(2):  # the second request is served from the kept grant
        assert transition(client, node).status_code == 503  # allowed; no gateway in unit tests
    from lifecycle_site.audit.models import TransitionRecord

    records = TransitionRecord.objects.filter(node=node)
    assert [(r.requested_by_id, r.requested_by_name) for r in records] == [(user.pk, "olga-token")] * 2
    grant = grants.cached(next(iter(grants._grants)))
    assert grant.user() is not grant.user() and grant.user().has_perm("fleet.operate_node")


def test_a_deleted_token_stops_at_once(db):
    client, record = token_client(make_user("tess-token", "viewer"))
    assert client.get("/api/v1/robots").status_code == 200
    record.delete()
    assert client.get("/api/v1/robots").status_code == 401


def test_a_deactivated_user_stops_at_once(db, settings):
    from lifecycle_site.audit.models import AccessDenial

    user = make_user("tess-token", "viewer")
    client, _ = token_client(user)
    assert client.get("/api/v1/robots").status_code == 200
    user.is_active = False
    user.save()
    for _ in range(settings.AXES_FAILURE_LIMIT * 4 + 1):  # a line PC that keeps trying: said why, never blocked
        answer = client.get("/api/v1/robots")
        assert answer.status_code == 401 and answer.json()["error"]["code"] == "account_off", answer.content
    assert "tess-token, whose account is switched off" in answer.json()["error"]["message"]
    assert AccessDenial.objects.filter(code="account_off").exists()
    assert not AccessDenial.objects.filter(code="bad_token").exists()
    user.is_active = True
    user.save()
    assert client.get("/api/v1/robots").status_code == 200


def test_a_lost_role_stops_at_once_however_it_is_lost(node):
    user = make_user("olga-token", "operator")
    client, _ = token_client(user)
    operator = Group.objects.get(name="operator")
    assert transition(client, node).status_code == 503

    user.groups.remove(operator)
    assert transition(client, node).status_code == 403
    user.groups.add(operator)
    assert transition(client, node).status_code == 503

    operator.user_set.remove(user)  # the reverse side of the same relation
    assert transition(client, node).status_code == 403
    operator.user_set.add(user)
    assert transition(client, node).status_code == 503

    operate = Permission.objects.get(codename="operate_node")
    operator.permissions.remove(operate)
    assert transition(client, node).status_code == 403
    operator.permissions.add(operate)
    assert transition(client, node).status_code == 503

    operator.delete()  # memberships go without an m2m signal
    assert transition(client, node).status_code == 403


def test_changes_made_by_another_process_take_effect_within_the_ttl(db, monkeypatch):
    monkeypatch.setattr(grants, "TOKEN_CACHE_TTL", 0.2)
    user = make_user("tess-token", "viewer")
    client, _ = token_client(user)
    assert client.get("/api/v1/robots").status_code == 200
    type(user).objects.filter(pk=user.pk).update(is_active=False)  # no signal, as from another process
    assert client.get("/api/v1/robots").status_code == 200  # still kept
    time.sleep(0.25)
    assert client.get("/api/v1/robots").status_code == 401


def test_the_kept_grants_are_bounded_least_recently_used_first(db, monkeypatch):
    monkeypatch.setattr(grants, "TOKEN_CACHE_SIZE", 2)
    user = make_user("tess-token", "viewer")
    clients = [token_client(user)[0] for _ in range(3)]
    for client in clients + clients[:1]:
        assert client.get("/api/v1/robots").status_code == 200
    assert len(grants._grants) == 2
    digests = [hash_token(c.defaults["HTTP_AUTHORIZATION"].split()[1]) for c in clients]
    assert list(grants._grants) == [digests[2], digests[0]]


def test_a_grant_read_while_it_was_invalidated_is_not_kept(db, monkeypatch):
    _, record = token_client(make_user("tess-token", "viewer"))

    class InvalidatedMeanwhile(grants._Grant):
        def __init__(self, record):
            super().__init__(record)
            grants.forget()  # a revocation lands between the query and the store

    monkeypatch.setattr(grants, "_Grant", InvalidatedMeanwhile)
    assert grants.load(record.digest) is not None
    assert record.digest not in grants._grants


def test_last_used_is_written_again_once_a_minute_old(db):
    client, record = token_client(make_user("tess-token", "viewer"))
    client.get("/api/v1/robots")
    old = timezone.now() - timedelta(minutes=5)
    ApiToken.objects.filter(pk=record.pk).update(last_used=old)
    grants.forget()
    client.get("/api/v1/robots")
    record.refresh_from_db()
    assert record.last_used > old


def test_unknown_tokens_are_refused_and_not_kept(db):
    response = Client(headers={"Authorization": "Bearer lcm_nonsense"}).get("/api/v1/robots")
    assert response.status_code == 401 and not grants._grants


# --- a gateway's heartbeat ------------------------------------------------------------------

def test_the_heartbeat_answer_is_kept_for_a_moment_only(db, redis_server, monkeypatch):
    monkeypatch.setattr(gateways, "BEAT_CACHE_S", 0.2)
    key = protocol.beat_key(gateways.channel_prefix(), "gw")
    stack.redis_client().delete(key)
    assert gateways.status("gw").state == "never"
    beat = stack.write_beat("gw")
    assert gateways.status("gw").online
    stack.redis_client().set(key, protocol.encode({**beat, "stopped": True}))  # as from the gateway's process
    assert gateways.status("gw").online  # kept
    time.sleep(0.25)
    assert gateways.status("gw").state == "stopped"
    with pytest.raises(gateway_client.GatewayOffline, match=r"^Gateway gw is offline \(it stopped at "):
        gateway_client.call_gateway("gw", protocol.GET_STATE, robot="cache-agv", node="/joy_to_vel")


def test_changed_settings_are_seen_at_once(db, redis_server, settings):
    stack.write_beat("gw")
    assert gateways.status("gw").online
    with override_settings(LIFECYCLE={**settings.LIFECYCLE, "GATEWAY_OFFLINE_AFTER": -3600}):
        assert not gateways.status("gw").online
    assert gateways.status("gw").online


# --- fleet rows -----------------------------------------------------------------------------

KEYS = ["agv-1.joy_to_vel", "agv-1.arm.gripper", "odd key:@!$&'()*+,;=~%é"]


@pytest.mark.parametrize("prefix", [None, "/edge/lifecycle"])
def test_row_links_are_what_reverse_gives_under_the_script_prefix(prefix):
    with script_prefix(prefix):
        nodes = [{"id": key} for key in KEYS]
        snapshots.with_links(nodes)
        for key, node in zip(KEYS, nodes, strict=True):
            assert node["url"] == reverse("dashboard:node", args=[key])
            assert node["transition_url"] == reverse("dashboard:node-transition", args=[key])
            assert node["url"].startswith((prefix or "") + "/nodes/")


def test_a_pushed_row_is_the_same_markup_as_in_the_fleet_list():
    nodes = [protocol.node_payload(key=f"agv-1.n{i}", robot="agv-1", name=f"/n{i}", state_id=state, alive=alive,
                                   last_seen=None if i == 0 else "2026-01-01T10:00:00+00:00")
             for i, (state, alive) in enumerate([(sm.UNKNOWN, False), (sm.ACTIVE, True), (sm.INACTIVE, True),
                                                 (sm.ACTIVATING, True), (sm.INACTIVE, False)])]
    local = Gateway(name="local")
    robot = Robot(name="agv-1", domain_id=1, gateway=local)
    snapshots.with_links(nodes)
    gateway = gateways.describe(local, gateways.GatewayStatus("local", gateways.NEVER), ["agv-1"])
    page = render_to_string("dashboard/_robots.html", {"gateways": [{"gateway": gateway, "robots": [(robot, nodes)]}],
                                                       "can_operate": True})
    assert page.count('class="node-row') == 5 and 'hx-post="/nodes/agv-1.n2/transition"' in page
    for node in nodes:
        row = render_to_string("dashboard/_node_row.html", {"nodes": [snapshots.fleet_row(node)], "oob": "",
                                                            "can_operate": True})
        assert row.count("<tr") == 1 and row in page


@pytest.fixture
def memory_layer(settings):
    settings.CHANNEL_LAYERS = {"default": {"BACKEND": "channels.layers.InMemoryChannelLayer"}}
    settings.LIFECYCLE_TRUST_FORWARDED_PREFIX = True


def test_fleet_socket_snapshot_is_rendered_off_the_event_loop_under_the_prefix(transactional_db, memory_layer,
                                                                                 monkeypatch):
    from lifecycle_site.dashboard.routing import websocket_urlpatterns

    robot = Robot.objects.create(name="ws-agv", domain_id=96)
    ManagedNode.objects.create(robot=robot, name="/lidar", alive=True, state_id=sm.ACTIVE, state_label="active")
    user = make_user("olga-socket", "operator")
    session = session_of(user)
    threads = {}
    fleet, render = snapshots.fleet, consumers.render_to_string

    def spied_fleet():
        threads["read"] = threading.get_ident()
        return fleet()

    def spied_render(template, *args, **kwargs):
        threads.setdefault(template, threading.get_ident())
        return render(template, *args, **kwargs)

    monkeypatch.setattr(snapshots, "fleet", spied_fleet)
    monkeypatch.setattr(consumers, "render_to_string", spied_render)

    async def scenario():
        threads["loop"] = threading.get_ident()
        communicator = WebsocketCommunicator(URLRouter(websocket_urlpatterns), "/ws/fleet/",
                                             headers=[(b"x-forwarded-prefix", b"/lifecycle")])
        communicator.scope["user"] = user
        communicator.scope["session"] = session
        connected, _ = await communicator.connect(timeout=5)
        assert connected
        try:
            snapshot = await receive_until(communicator, 'id="robots"')
            assert 'href="/lifecycle/nodes/ws-agv.lidar/"' in snapshot
            assert 'hx-post="/lifecycle/nodes/ws-agv.lidar/transition"' in snapshot
            layer = get_channel_layer()
            for name, state in (("/lidar", sm.INACTIVE), ("/camera", sm.UNCONFIGURED)):
                payload = protocol.node_payload(key=f"ws-agv.{name[1:]}", robot="ws-agv", name=name,
                                                state_id=state, alive=True, last_seen=None)
                await layer.group_send(protocol.FLEET_GROUP, {"type": "node.state", "node": payload})
            changed = await receive_until(communicator, 'id="node-ws-agv__lidar"')
            assert 'hx-swap-oob="true"' in changed and ">activate</button>" in changed
            assert 'href="/lifecycle/nodes/ws-agv.lidar/"' in changed
            added = await receive_until(communicator, 'id="node-ws-agv__camera"')
            assert 'hx-swap-oob="beforeend:#robot-ws-agv-nodes"' in added
            assert 'hx-post="/lifecycle/nodes/ws-agv.camera/transition"' in added
        finally:
            await communicator.disconnect()

    async_to_sync(scenario)()
    assert threads["loop"] not in (threads["read"], threads["dashboard/_robots.html"])
