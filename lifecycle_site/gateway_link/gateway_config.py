"""The config each gateway follows (``P:gw:NAME:config``: its robots, their nodes' order and
desired states, and what its Redis keys may hold), published when a robot or node changes and by
the ingest process at least every minute (protocol: ros_gateway/shared/protocol.py)."""
from __future__ import annotations

import hashlib
import logging
import threading
import time
from typing import Iterable

import redis
from django.conf import settings
from django.db import transaction
from django.db.models.signals import post_delete, post_save

from lifecycle_site.fleet.models import Gateway, ManagedNode, ProcessProfile, Robot
from lifecycle_site.gateway_link.gateways import channel_prefix, redis_client
from lifecycle_site.modes.models import CurrentMode, Mode
from ros_gateway.shared import protocol

log = logging.getLogger(__name__)


def build_config(gateway_name: str) -> dict:
    """What a gateway watches: its enabled robots, their nodes' order and desired state, and
    the processes it runs for them (their launch profiles)."""
    robots = list(Robot.objects.filter(gateway__name=gateway_name, enabled=True).order_by("name"))
    nodes: dict[int, dict[str, dict]] = {r.id: {} for r in robots}
    robot_keep = {r.id: r.keep_desired for r in robots}
    rows = ManagedNode.objects.filter(robot__in=robots).order_by("name").values_list(
        "robot_id", "name", "order", "desired_state", "keep_desired", "enforcement_stopped", "enforcement_resumed"
    )
    for robot_id, name, order, desired, keep, stopped, resumed in rows:
        keep = keep or robot_keep[robot_id]  # (as ManagedNode.keep says, without a query per node)
        keep = protocol.KEEP_PAUSED if keep == "enforce" and stopped else keep
        nodes[robot_id][name] = {"order": order, "desired_state": desired, "keep": keep,
                                 **({"resumed": resumed.isoformat()} if resumed else {})}
    processes: dict[int, list[dict]] = {r.id: [] for r in robots}
    for profile in ProcessProfile.objects.filter(robot__in=robots, enabled=True).order_by("name"):
        processes[profile.robot_id].append(profile.for_gateway())
    # The topics whose rates the robots' current modes wait for (lifecycle_site/modes/readiness.py).
    rates = {m.robot_id: m.topics()[:protocol.MAX_RATE_TOPICS]
             for m in CurrentMode.objects.filter(robot__in=robots).select_related("mode")}
    body = {
        "gateway": gateway_name,
        "robots": [
            {"id": r.id, "name": r.name, "domain_id": r.domain_id, "namespace": r.namespace,
             "auto_recover": r.auto_recover, "nodes": nodes[r.id], "processes": processes[r.id],
             **({"rates": rates[r.id]} if rates.get(r.id) else {})}
            for r in robots
        ],
    }
    body["limits"] = {"redis_bytes": redis_quota(),
                      "diagnostics_stale_s": settings.LIFECYCLE["DIAGNOSTICS_STALE_S"]}
    version = hashlib.sha256(protocol.encode(body).encode()).hexdigest()[:16]
    return {"gateway": gateway_name, "version": version, "robots": body["robots"], "limits": body["limits"]}


# --- what a gateway may hold in Redis ---------------------------------------------------------

QUOTA_CAP = 64 * 1024 * 1024
QUOTA_FLOOR = 1024 * 1024
QUOTA_READ_EVERY_S = 10.0
_quota: tuple[float, int] = (-QUOTA_READ_EVERY_S, protocol.DEFAULT_REDIS_QUOTA)


def redis_quota(client: redis.Redis | None = None) -> int:
    """Bytes each gateway's Redis keys may hold (gateway_link/redis_guard.py cuts off one beyond):
    LIFECYCLE_GATEWAY_REDIS_QUOTA_MB, else an eighth of Redis's maxmemory (at most 64 MB; 64 MB
    without a maxmemory), else, when Redis will not say, protocol.DEFAULT_REDIS_QUOTA."""
    global _quota
    configured = settings.LIFECYCLE.get("GATEWAY_REDIS_QUOTA")
    if configured:
        return int(configured)
    read_at, quota = _quota
    if time.monotonic() - read_at < QUOTA_READ_EVERY_S:
        return quota
    try:
        maxmemory = int((client or redis_client()).config_get("maxmemory").get("maxmemory") or 0)
        quota = max(QUOTA_FLOOR, min(QUOTA_CAP, maxmemory // 8)) if maxmemory else QUOTA_CAP
    except (redis.RedisError, ValueError):
        quota = protocol.DEFAULT_REDIS_QUOTA
    _quota = (time.monotonic(), quota)
    return quota


def publish_config(gateway_name: str, client: redis.Redis | None = None) -> dict:
    """Write the gateway's config key; returns the config. Raises redis.RedisError."""
    config = build_config(gateway_name)
    (client or redis_client()).set(protocol.config_key(channel_prefix(), gateway_name), protocol.encode(config))
    return config


_pending = threading.local()


def publish_on_commit(gateway_names: Iterable[str]) -> None:
    """Publish these gateways' configs once the current transaction commits (once each, however
    many changes it holds). A Redis failure is logged: the ingest process publishes again."""
    waiting: set[str] | None = getattr(_pending, "names", None)
    if waiting is None:
        waiting = _pending.names = set()
    waiting.update(gateway_names)
    transaction.on_commit(_publish_pending)  # the first callback to run publishes them all


def _publish_pending() -> None:
    names, _pending.names = getattr(_pending, "names", None) or set(), set()
    for name in sorted(names):
        try:
            publish_config(name)
        except redis.RedisError as exc:
            log.warning("could not publish the config of gateway %s (Redis: %s); the ingest process will", name, exc)


CONFIG_FIELDS = {"name", "order", "desired_state", "robot", "robot_id", "keep_desired", "enforcement_stopped",
                 "enforcement_resumed"}


def _robot_changed(sender, instance: Robot, **kwargs) -> None:
    # A robot may have moved from one gateway to another: every gateway's config is rebuilt
    # (a handful of small queries), so the one it left forgets it too.
    publish_on_commit(Gateway.objects.values_list("name", flat=True))


def _node_changed(sender, instance: ManagedNode, created: bool = False, update_fields=None, **kwargs) -> None:
    if kwargs.get("signal") is post_save and not created and update_fields is not None \
            and not CONFIG_FIELDS & set(update_fields):
        return
    gateway = Robot.objects.filter(pk=instance.robot_id).values_list("gateway__name", flat=True).first()
    if gateway:
        publish_on_commit([gateway])


def _profile_changed(sender, instance: ProcessProfile, **kwargs) -> None:
    gateway = Robot.objects.filter(pk=instance.robot_id).values_list("gateway__name", flat=True).first()
    if gateway:
        publish_on_commit([gateway])


def _mode_changed(sender, instance: Mode, **kwargs) -> None:
    """A mode's readiness may name other topics: the gateways of the robots in it measure those."""
    publish_on_commit(set(CurrentMode.objects.filter(mode=instance).values_list("robot__gateway__name", flat=True)))


post_save.connect(_mode_changed, sender=Mode, dispatch_uid="gateway_link.gateways.mode_saved")
post_save.connect(_profile_changed, sender=ProcessProfile, dispatch_uid="gateway_link.gateways.profile_saved")
post_delete.connect(_profile_changed, sender=ProcessProfile, dispatch_uid="gateway_link.gateways.profile_deleted")
post_save.connect(_robot_changed, sender=Robot, dispatch_uid="gateway_link.gateways.robot_saved")
post_delete.connect(_robot_changed, sender=Robot, dispatch_uid="gateway_link.gateways.robot_deleted")
post_save.connect(_node_changed, sender=ManagedNode, dispatch_uid="gateway_link.gateways.node_saved")
post_delete.connect(_node_changed, sender=ManagedNode, dispatch_uid="gateway_link.gateways.node_deleted")
