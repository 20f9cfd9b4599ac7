"""One ROS domain: its own rclpy Context, the gateway's nodes in it, and their threads.

Everything rclpy touches lives here and in rosout_reader.py (which a domain starts). Callbacks
run on executor threads and are handed to the gateway's asyncio loop with
``call_soon_threadsafe``; service calls return asyncio results with a hard timeout.

Threads per domain: one executor for the graph and /parameter_events, one reader of /rosout
(rosout_reader.py), and one executor per *shard* of watched nodes. An rclpy executor rebuilds
its wait set over all its entities for every message it takes, so one executor holding every
node's event subscription and service clients gets slower with each node the domain has (a
ChangeState call took 12.6 ms at 100 nodes against 2.7 ms at one). Shards keep that cost
flat: each holds the entities of at most NODES_PER_SHARD watched nodes.
"""
from __future__ import annotations

import asyncio
import logging
import math
import os
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterable

import rclpy
from lifecycle_msgs.msg import TransitionEvent
from rcl_interfaces.msg import ParameterEvent
from rclpy.context import Context
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.qos import qos_profile_parameter_events

from ros_gateway.rosout_reader import RosoutReader

log = logging.getLogger(__name__)

GET_STATE_TYPE = "lifecycle_msgs/srv/GetState"
# The gateway's Fast DDS defaults (see the file for why); read when the first Context starts.
FASTDDS_PROFILES = Path(__file__).with_name("fastdds_gateway.xml")
# After a domain starts, discovery needs a moment before "not in the graph" means "gone"
# (nodes the site believes alive are reported lost only after it).
DISCOVERY_SETTLE_S = 3.0
# A command for a node not found yet waits longer: the gateway announces itself 5 times 100 ms
# apart, then every second (fastdds_gateway.xml); the robots every 3 s. Seen in CI: a restarted
# gateway found the robots 3.03 s after it started and called a running node "not running".
COMMAND_DISCOVERY_WAIT_S = 6.0
# Watched nodes per shard (its own rclpy node, executor and thread).
NODES_PER_SHARD = 12
# A node whose process ended keeps its clients and event subscription this long: the next process
# under its name (a restart; a crash's respawn after its back-off, up to 30 s unless its profile asks
# for a longer delay) matches them while it starts, so the first calls into it are answered at once
# instead of after a new client's own discovery (0.2-0.5 s after 50 nodes appeared at once). Kept,
# they hold their places on their shard and are matched by DDS, but nothing is sent or handed on.
KEEP_GONE_S = 35.0
# The service list (thousands of entries in a big domain) is re-read on each discovery pass
# while the set of running nodes changes and for a while after; otherwise this often.
SERVICE_SCAN_SETTLE_S = 5.0
SERVICE_SCAN_EVERY_S = 2.0
# Services that only read: a request left unanswered is sent again. Fast DDS drops a
# response when the server's response writer has not matched the caller's response reader
# within 100 ms (its max_blocking_time; "client will not receive response"), which happens
# to the first calls of a client made just now and to the first calls into a process that
# restarted, on a busy machine: the call then waited its whole timeout (5 s) for nothing.
# Calls that change a node (change_state, set_parameters) are never sent twice.
READ_ONLY_SERVICES = frozenset({
    "get_state", "get_available_states", "get_available_transitions", "get_transition_graph",
    "list_parameters", "get_parameters", "describe_parameters", "get_parameter_types",
})
# A read is sent again every this long while unanswered (a well node answers in
# milliseconds; 6 requests at most within a 3 s timeout). A steady pace, not a growing one:
# the answer can come only to a request sent after the node matched us, and a gateway
# restarted after a kill is not answered for 1.0-3.4 s (docs/networks.md); with pauses that
# doubled, the last request of a 3 s call left at 1 s and its answer was lost.
RESEND_AFTER_S = 0.5


class ServiceTimeout(Exception):
    """The service did not answer within the bound."""


class ServiceUnavailable(Exception):
    """No server for the service appeared within the bound."""


def _gateway_node(context: Context, name: str) -> rclpy.node.Node:
    """A node of the gateway's own: no parameter services, and it does not log to /rosout."""
    return rclpy.create_node(name, context=context, start_parameter_services=False, enable_rosout=False)


class _Shard:
    """An rclpy node with an executor thread of its own, holding some watched nodes' entities."""

    def __init__(self, context: Context, domain_id: int, index: int) -> None:
        self.node = _gateway_node(context, f"lifecycle_gateway_{os.getpid()}_{index}")
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.watched: set[str] = set()  # fully qualified names of the nodes placed here
        self.thread = threading.Thread(
            target=_spin, args=(self.executor, domain_id), name=f"ros-domain-{domain_id}-{index}", daemon=True
        )
        self.thread.start()

    def stop(self) -> None:
        self.executor.shutdown(timeout_sec=2.0)
        self.node.destroy_node()


def _spin(executor: SingleThreadedExecutor, domain_id: int) -> None:
    """Spin until the domain stops. A failure inside a spin does not end the thread: when many
    nodes vanish at once (a process of 50 stopped), their subscriptions and clients are destroyed
    from the gateway's loop while this thread waits on them, and rclpy raises InvalidHandle for
    the destroyed one; the executor, spun again, waits on what is left. A thread that had ended
    here left every node placed on its shard unanswered for good."""
    failures: list[float] = []
    while True:
        try:
            executor.spin()
            return
        except (ExternalShutdownException, rclpy.executors.ShutdownException):
            return
        except Exception:  # noqa: BLE001 - logged; the executor goes on
            now = time.monotonic()
            failures = [t for t in failures if now - t < 10.0] + [now]
            log.warning("an executor of ROS domain %d failed (%d time(s) in 10 s); spinning on", domain_id,
                        len(failures), exc_info=len(failures) == 1)
            if not executor.context.ok():
                return
            time.sleep(min(1.0, 0.01 * 2 ** min(len(failures), 7)))  # a failure that repeats does not spin hot


class RosDomain:
    """The gateway's presence in one ROS domain."""

    def __init__(
        self,
        domain_id: int,
        loop: asyncio.AbstractEventLoop,
        on_transition_event: Callable[[int, str, Any], None],
        on_log: Callable[[int, Any], None],
        on_parameter_event: Callable[[int, Any], None] | None = None,
    ) -> None:
        self.domain_id = domain_id
        self.loop = loop
        self._on_transition_event = on_transition_event
        self._on_log = on_log
        self._on_parameter_event = on_parameter_event
        self.context = Context()
        self.node: rclpy.node.Node | None = None
        self.executor: SingleThreadedExecutor | None = None
        self._thread: threading.Thread | None = None
        self._shards: list[_Shard] = []
        self._shard_of: dict[str, _Shard] = {}  # watched node -> its shard
        self._clients: dict[tuple[str, str], Any] = {}
        self._event_subscriptions: dict[str, Any] = {}
        self._kept: dict[str, float] = {}  # gone nodes whose entities are kept -> until (monotonic)
        self._log_node: rclpy.node.Node | None = None
        self._rosout: RosoutReader | None = None
        self.started_at = 0.0
        self._running: set[str] = set()  # running nodes at the last discovery pass
        self._lifecycle: set[str] = set()  # of those, the ones offering GetState at the last scan
        self._last_change = self._last_scan = 0.0
        self._meter: _Shard | None = None  # topics whose rates are measured (topic_rates.py)

    # -- life of the domain ---------------------------------------------------------
    def start(self) -> None:
        # Discovery range and static peers come from the environment (ROS_AUTOMATIC_DISCOVERY_RANGE,
        # ROS_STATIC_PEERS) exactly as for any ROS process; only the domain id is ours to set.
        os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(FASTDDS_PROFILES))
        rclpy.init(context=self.context, domain_id=self.domain_id)
        self.node = _gateway_node(self.context, f"lifecycle_gateway_{os.getpid()}")
        self._log_node = _gateway_node(self.context, f"lifecycle_gateway_logs_{os.getpid()}")
        self._rosout = RosoutReader(self._log_node, self.domain_id, self._on_log)  # its own thread
        if self._on_parameter_event is not None:
            self.node.create_subscription(
                ParameterEvent,
                "/parameter_events",
                lambda msg: self._hand_over(self._on_parameter_event, self.domain_id, msg),
                qos_profile_parameter_events,
            )
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(
            target=_spin, args=(self.executor, self.domain_id), name=f"ros-domain-{self.domain_id}", daemon=True
        )
        self._thread.start()
        self._rosout.start()
        self.started_at = time.monotonic()
        log.info("watching ROS domain %d", self.domain_id)

    def stop(self) -> None:
        try:
            if self._rosout is not None:
                self._rosout.stop()
            for shard in [*self._shards, *([self._meter] if self._meter else [])]:
                shard.stop()
            if self.executor is not None:
                self.executor.shutdown(timeout_sec=2.0)
            if self._log_node is not None:
                self._log_node.destroy_node()
            if self.node is not None:
                self.node.destroy_node()
        finally:
            if self.context.ok():
                self.context.try_shutdown()
            if self._thread is not None:
                self._thread.join(timeout=3.0)
            for shard in [*self._shards, *([self._meter] if self._meter else [])]:
                shard.thread.join(timeout=3.0)
        log.info("stopped watching ROS domain %d", self.domain_id)

    def meter_node(self) -> rclpy.node.Node:
        """A node with an executor thread of its own for the topics whose rates are measured (a busy
        topic's messages do not wait behind, nor delay, the lifecycle nodes' events)."""
        if self._meter is None:
            self._meter = _Shard(self.context, self.domain_id, 999)
        return self._meter.node

    def topic_types(self) -> dict[str, list[str]]:
        return dict(self.node.get_topic_names_and_types()) if self.node is not None else {}

    def settling(self, window: float = DISCOVERY_SETTLE_S) -> bool:
        """Whether discovery in this domain is too young to call a node missing."""
        return time.monotonic() - self.started_at < window

    # -- graph ----------------------------------------------------------------------
    def lifecycle_node_names(self, known: Iterable[str] = ()) -> set[str]:
        """Fully qualified names of running nodes offering lifecycle_msgs/srv/GetState.

        A service name alone is not proof of life: our own clients keep ``X/get_state`` in
        the graph after X is gone, so the node must also be listed as a running node. The
        node list is cheap and read every time; the service list only when needed (above).

        A node that still publishes its transition events counts as running even when the node
        list lacks it. The node list comes from one message per process (ros_discovery_info)
        and can stay behind: rmw_fastrtps does not list again the nodes of a participant that
        was dropped for its lease (a host away longer than ~20 s) and then found again, and a
        process that made 50 nodes at once on a loaded machine was seen listed with 21 of them
        for minutes. Endpoints are discovered on their own, so a publisher on
        ``X/transition_event`` (which our own clients never make) is proof of life. Checked for
        ``known`` nodes and for every node offering GetState that the list lacks.
        """
        listed = {
            f"{namespace.rstrip('/')}/{name}" for name, namespace in self.node.get_node_names_and_namespaces()
        }
        now = time.monotonic()
        if listed != self._running:
            self._running, self._last_change = listed, now
        if now - self._last_change < SERVICE_SCAN_SETTLE_S or now - self._last_scan >= SERVICE_SCAN_EVERY_S:
            self._last_scan = now
            self._lifecycle = {
                service[: -len("/get_state")]
                for service, types in self.node.get_service_names_and_types()
                if GET_STATE_TYPE in types and service.endswith("/get_state")
            }
        unlisted = (self._lifecycle | set(known)) - listed
        publishing = {fqn for fqn in unlisted if self.node.count_publishers(f"{fqn}/transition_event")}
        return (self._lifecycle & listed) | publishing

    def _shard_for(self, fqn: str) -> _Shard:
        """The node's shard: where it was placed, else the least loaded one with room, else a new one."""
        shard = self._shard_of.get(fqn)
        if shard is None:
            shard = min(self._shards, key=lambda s: len(s.watched), default=None)
            if shard is None or len(shard.watched) >= NODES_PER_SHARD:
                shard = _Shard(self.context, self.domain_id, len(self._shards))
                self._shards.append(shard)
            shard.watched.add(fqn)
            self._shard_of[fqn] = shard
        return shard

    def watch_node(self, fqn: str) -> None:
        """Subscribe to the node's transition events."""
        self._kept.pop(fqn, None)
        if fqn in self._event_subscriptions:
            return
        self._event_subscriptions[fqn] = self._shard_for(fqn).node.create_subscription(
            TransitionEvent,
            f"{fqn}/transition_event",
            lambda msg, fqn=fqn: fqn in self._kept or self._hand_over(self._on_transition_event, self.domain_id,
                                                                      fqn, msg),
            10,
        )

    def incarnation(self, fqn: str) -> frozenset:
        """Ids of the endpoints publishing the node's transition events: a process that
        restarts under the same name gets new ones, even while the old are still listed. Before
        that publisher is discovered, its /rosout publisher's (the same process: a restart seen)."""
        infos = self.node.get_publishers_info_by_topic(f"{fqn}/transition_event")
        if not infos:  # not discovered yet: its /rosout publisher (made with the node) tells its process too
            namespace, _, name = fqn.rpartition("/")
            infos = [info for info in self.node.get_publishers_info_by_topic("/rosout")
                     if info.node_name == name and info.node_namespace == (namespace or "/")]
        return frozenset(bytes(info.endpoint_gid) for info in infos)

    def own_gid(self) -> bytes | None:
        """An endpoint id of the gateway's own participant in this domain (its GUID prefix
        tells which host this is, see processes.py)."""
        name = self.node.get_name()
        for info in self.node.get_publishers_info_by_topic("/parameter_events"):
            if info.node_name == name:
                return bytes(info.endpoint_gid)
        return None

    def forget_node(self, fqn: str, *, keep: bool = False) -> None:
        """Drop the node's subscription and clients (it left our robots). ``keep``: its process
        ended or left; they are kept for KEEP_GONE_S (its events not handed on meanwhile), for a
        process that comes back under its name (drop_kept ends them)."""
        if keep and fqn in self._shard_of:
            self._kept[fqn] = time.monotonic() + KEEP_GONE_S
            return
        shard = self._shard_of.pop(fqn, None)
        if shard is not None:
            shard.watched.discard(fqn)
            subscription = self._event_subscriptions.pop(fqn, None)
            if subscription is not None:
                shard.node.destroy_subscription(subscription)
            for key in [k for k in self._clients if k[0] == fqn]:
                shard.node.destroy_client(self._clients.pop(key))
        self._kept.pop(fqn, None)  # (after: an event of a kept node is not handed on while it goes)

    def drop_kept(self) -> None:
        """Forget the gone nodes kept longer than KEEP_GONE_S."""
        now = time.monotonic()
        for fqn in [fqn for fqn, until in self._kept.items() if until <= now]:
            self.forget_node(fqn)

    # -- service calls --------------------------------------------------------------
    async def call(self, fqn: str, service: str, srv_type: Any, request: Any, timeout: float) -> Any:
        """Call ``{fqn}/{service}``; raises ServiceUnavailable or ServiceTimeout within ``timeout``.
        A read-only service's request is sent again while unanswered (READ_ONLY_SERVICES)."""
        deadline = time.monotonic() + timeout
        client = self._clients.get((fqn, service))
        if client is None:
            client = self._shard_for(fqn).node.create_client(srv_type, f"{fqn}/{service}")
            self._clients[(fqn, service)] = client
        result: asyncio.Future = self.loop.create_future()

        def done(ros_future) -> None:
            self.loop.call_soon_threadsafe(_settle, result, ros_future)

        sent: list = []

        def send() -> None:
            ros_future = client.call_async(request)
            sent.append(ros_future)
            ros_future.add_done_callback(done)

        try:
            try:
                # A fresh client needs a moment to match the server (about 0.25 s on loopback).
                while not client.service_is_ready():
                    if time.monotonic() >= deadline:
                        raise ServiceUnavailable(f"{fqn}/{service} is not available")
                    await asyncio.sleep(0.02)
                send()
            except _rclpy.InvalidHandle:  # the node was forgotten (gone) meanwhile, and its client with it
                raise ServiceUnavailable(f"{fqn}/{service} is no longer watched (the node went)") from None
            resend_after = RESEND_AFTER_S if service in READ_ONLY_SERVICES else math.inf
            while True:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise ServiceTimeout(f"{fqn}/{service} did not answer within {timeout:g} s")
                await asyncio.wait([result], timeout=min(left, resend_after))
                if result.done():
                    return result.result()
                if time.monotonic() < deadline and resend_after < math.inf:
                    log.debug("%s/%s unanswered after %g s: asked again", fqn, service, resend_after)
                    try:
                        send()
                    except _rclpy.InvalidHandle:  # forgotten meanwhile: the requests sent may still be answered
                        resend_after = math.inf
        finally:  # the caller stopped waiting, or an answer came: the other requests are not awaited
            for ros_future in sent:
                if not ros_future.done():
                    client.remove_pending_request(ros_future)

    # -- callbacks (executor thread) ------------------------------------------------
    def _hand_over(self, callback: Callable, *args: Any) -> None:
        try:
            self.loop.call_soon_threadsafe(callback, *args)
        except RuntimeError:  # loop closed while shutting down
            pass


def _settle(result: asyncio.Future, ros_future: Any) -> None:
    if result.done():
        return
    exception = ros_future.exception()
    if exception is not None:
        result.set_exception(exception)
    else:
        result.set_result(ros_future.result())
