"""The site's view of its gateways through Redis: heartbeats and quarantines (the config each
one follows: gateway_config.py; the Redis user each one connects with: redis_users.py;
protocol: ros_gateway/shared/protocol.py).

Whether a gateway is online comes from its heartbeat key, read at most once a second per
gateway in each process; pages add what the ingest process copied into the Gateway row.
"""
from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from functools import lru_cache
from typing import Any, Iterable
from urllib.parse import urlsplit, urlunsplit

import redis
from django.conf import settings
from django.core.signals import setting_changed
from django.utils.translation import gettext as _
from django.utils.translation import ngettext
from redis.backoff import ExponentialBackoff
from redis.retry import Retry

from lifecycle_site.fleet.models import Gateway
from lifecycle_site.gateway_link import presence
from lifecycle_site.gateway_link.stream_entries import beat_at, beat_started, plausible
from ros_gateway.shared import protocol

log = logging.getLogger(__name__)

# Upper bound of a service timeout a caller may ask for, so every wait on Redis stays bounded.
MAX_SERVICE_TIMEOUT = 25.0


def channel_prefix() -> str:
    return settings.CHANNEL_LAYERS["default"].get("CONFIG", {}).get("prefix", "lifecycle")


# Every read of the site's Redis answers within this (a reply is awaited in blocking pops of
# at most a second each: gateway_client.WAIT_SLICE_S), so a Redis that hangs (stopped, or
# cut off without a reset) makes a request answer 503 after seconds, not minutes.
SOCKET_TIMEOUT_S = 3.0


@lru_cache(maxsize=1)
def redis_client() -> redis.Redis:
    """The site's connection pool to Redis (the default user: it manages the gateways' users).

    A connection the pool kept across a Redis restart is dead: its command is tried again on
    a fresh one (ConnectionError). A timeout is not tried again: a Redis that does not answer
    would only make the user wait three times as long for the same 503."""
    return redis.Redis.from_url(
        settings.REDIS_URL, socket_connect_timeout=2, socket_timeout=SOCKET_TIMEOUT_S, client_name=presence.SITE_CLIENT,
        retry_on_error=[redis.ConnectionError],
        retry=Retry(ExponentialBackoff(cap=0.5, base=0.05), 2, supported_errors=(redis.ConnectionError,)),
        health_check_interval=30,
    )


def safe_url(url: str) -> str:
    """A Redis URL fit for a log: without its password."""
    parts = urlsplit(url)
    if parts.password is None:
        return url
    host = parts.hostname or ""
    if ":" in host:
        host = f"[{host}]"
    netloc = f"{parts.username or ''}:***@{host}" + (f":{parts.port}" if parts.port else "")
    return urlunsplit(parts._replace(netloc=netloc))


# --- heartbeats -----------------------------------------------------------------------------

# How long a process trusts its last look at a gateway's heartbeat (a Redis round trip on
# every command otherwise). A gateway that stops cleanly says so in its heartbeat, so commands
# are refused with the clear "offline" error at most this long after it stopped.
BEAT_CACHE_S = 1.0
_beats: dict[str, tuple[float, dict | None, str, dict | None]] = {}  # name -> (read at, beat, Redis error, quarantine)
_beats_lock = threading.Lock()


def forget_beats() -> None:
    """Read heartbeats and quarantines afresh (this process just changed one)."""
    with _beats_lock:
        _beats.clear()


def forget(**_: Any) -> None:
    """Read heartbeats (and the Redis address) afresh: settings changed, or a test wrote one."""
    forget_beats()
    presence.forget()
    redis_client.cache_clear()


setting_changed.connect(forget, dispatch_uid="gateway_link.gateways.setting_changed")


def _parse_beat(raw: bytes | None) -> dict | None:
    if raw is None:
        return None
    try:
        beat = json.loads(raw)
        return beat if isinstance(beat, dict) else None
    except ValueError:
        return None


def quarantine_key(prefix: str | None = None) -> str:
    """The site's hash of quarantined gateways (gateway_link/quarantine.py): name -> {"since", "reason"}."""
    return f"{prefix or channel_prefix()}:site:quarantined"


def parse_quarantine(value: bytes | str | None) -> dict | None:
    """One entry of that hash as {"since": datetime | None, "reason": str}; None for no entry."""
    if value is None:
        return None
    try:
        data = json.loads(value)
    except ValueError:
        data = {}
    if not isinstance(data, dict):
        data = {}
    return {"since": _moment(data.get("since")), "reason": str(data.get("reason") or "")}


def _moment(text: Any) -> datetime | None:
    try:
        moment = datetime.fromisoformat(str(text))
    except ValueError:
        return None
    return moment if moment.tzinfo else moment.replace(tzinfo=timezone.utc)


def read_beats(names: Iterable[str]) -> dict[str, tuple[dict | None, str, dict | None]]:
    """Each gateway's heartbeat (or None), the Redis error that hid it (or "") and its
    quarantine (or None): one round trip for those not read within BEAT_CACHE_S."""
    names = list(dict.fromkeys(names))
    now = time.monotonic()
    with _beats_lock:
        kept = {n: _beats[n] for n in names if n in _beats and 0 <= now - _beats[n][0] < BEAT_CACHE_S}
    stale = [n for n in names if n not in kept]
    if stale:
        prefix = channel_prefix()
        try:
            with redis_client().pipeline(transaction=False) as pipe:
                pipe.mget([protocol.beat_key(prefix, n) for n in stale])
                pipe.hmget(quarantine_key(prefix), stale)
                raws, held = pipe.execute()
            read = time.monotonic()  # each beat was written before this
            fresh = {n: (read, _parse_beat(raw), "", parse_quarantine(q))
                     for n, raw, q in zip(stale, raws, held, strict=True)}
        except redis.RedisError as exc:
            fresh = {n: (now, None, str(exc) or type(exc).__name__, None) for n in stale}
        with _beats_lock:
            _beats.update(fresh)
        kept.update(fresh)
    return {n: kept[n][1:] for n in names}


def _when(moment: datetime, ago: bool = True) -> str:
    """'10:32:05 UTC, 2 min ago' (the date too when it is not today); without ``ago`` only the
    clock, for what is kept (an alert's message) or shown with an age the page keeps current."""
    moment = moment.astimezone(timezone.utc)
    now = datetime.now(timezone.utc)
    clock = moment.strftime("%H:%M:%S UTC") if moment.date() == now.date() else moment.strftime("%Y-%m-%d %H:%M UTC")
    if not ago:
        return clock
    seconds = max(0, int((now - moment).total_seconds()))
    if seconds < 120:
        ago = _("%(n)s s ago") % {"n": seconds}
    elif seconds < 7200:
        ago = _("%(n)s min ago") % {"n": seconds // 60}
    elif seconds < 172800:
        ago = _("%(n)s h ago") % {"n": seconds // 3600}
    else:
        days = seconds // 86400
        ago = ngettext("%(n)s day ago", "%(n)s days ago", days) % {"n": days}
    return f"{clock}, {ago}"


ONLINE, OFFLINE, STOPPED, NEVER, UNREACHABLE = "online", "offline", "stopped", "never", "unreachable"
QUARANTINED = "quarantined"  # cut off by the site (gateway_link/quarantine.py)
ENDED = "ended"  # a reason, not a status: OFFLINE because its process ended


@dataclass(frozen=True)
class GatewayStatus:
    """Whether a gateway can take commands now, and since when it cannot."""

    name: str
    state: str  # ONLINE, OFFLINE (silent), STOPPED (said so), NEVER (never reported), UNREACHABLE (Redis),
    #             QUARANTINED (cut off by the site)
    last_beat: datetime | None = None
    beat: dict = field(default_factory=dict)
    redis_error: str = ""
    ended: bool = False  # OFFLINE because its process has ended (its Redis connections closed)
    quarantined: datetime | None = None
    quarantine_reason: str = ""

    @property
    def online(self) -> bool:
        return self.state == ONLINE

    def reason(self, ago: bool = True) -> str:
        """Why it takes no commands, for a person: 'no heartbeat since 10:32:05 UTC, 2 min ago'
        (without ``ago``: 'no heartbeat since 10:32:05 UTC'). In the active language: what is
        stored (an alert's summary) takes it in English (refusal.in_english)."""
        if self.state == UNREACHABLE:
            return _("Redis, which links the site and its gateways, is unreachable: %(error)s") % {
                "error": self.redis_error.rstrip(".")}
        if self.state == QUARANTINED:
            why = self.quarantine_reason.rstrip(".")  # (stored, in English)
            if self.quarantined:
                return _("the site cut it off at %(when)s: %(reason)s") % {
                    "when": _when(self.quarantined, ago), "reason": why}
            return _("the site cut it off: %(reason)s") % {"reason": why}
        if self.state == NEVER or self.last_beat is None:
            return _("it has never reported")
        if self.state == STOPPED:
            return _("it stopped at %(when)s") % {"when": _when(self.last_beat, ago)}
        if self.ended:
            return _("its process has ended: its connection to Redis closed (last heartbeat %(when)s)") % {
                "when": _when(self.last_beat, ago)}
        return _("no heartbeat since %(when)s") % {"when": _when(self.last_beat, ago)}

    def reason_since(self) -> datetime | None:
        """The moment reason() counts its age from (None: it names none)."""
        if self.state == QUARANTINED:
            return self.quarantined
        if self.state in (UNREACHABLE, NEVER) or self.online:
            return None
        return self.last_beat

    def refusal(self, robot: str | None = None) -> str:
        """The error of a command that was not sent because of this status (in the active
        language; refusal.in_english for the stored one)."""
        values = {"gateway": self.name, "reason": self.reason(), "robot": robot}
        if self.state == UNREACHABLE:
            if robot:
                return _("%(reason)s; nothing was sent to %(robot)s (gateway %(gateway)s).") % values
            return _("%(reason)s; nothing was sent (gateway %(gateway)s).") % values
        if self.state == QUARANTINED:
            if robot:
                return _("Gateway %(gateway)s is quarantined (%(reason)s); nothing was sent to %(robot)s. An "
                         "administrator can lift the quarantine in the admin (Gateways) once the cause is dealt "
                         "with.") % values
            return _("Gateway %(gateway)s is quarantined (%(reason)s); nothing was sent. An administrator can lift "
                     "the quarantine in the admin (Gateways) once the cause is dealt with.") % values
        if robot:
            return _("Gateway %(gateway)s is offline (%(reason)s); nothing was sent to %(robot)s.") % values
        return _("Gateway %(gateway)s is offline (%(reason)s); nothing was sent.") % values

    def as_dict(self) -> dict:
        return {
            "name": self.name,
            "online": self.online,
            "status": self.state,
            "last_beat": self.last_beat.isoformat() if self.last_beat else None,
            "reason": "" if self.online else self.reason(),
            # For pages: the reason without its age, and the moment to count the age from (the
            # page keeps "N s ago" current; a stored "12 s ago" would never move on).
            "reason_plain": "" if self.online else self.reason(ago=False),
            "reason_since": since.isoformat() if (since := self.reason_since()) else None,
            "quarantined": self.quarantined.isoformat() if self.quarantined else None,
        }


def _status(name: str, beat: dict | None, error: str, quarantined: dict | None, known_last_beat: datetime | None,
            read_at: float = 0.0) -> GatewayStatus:
    known_last_beat = plausible(known_last_beat)  # (a row may hold one stored before times were checked)
    if quarantined is not None:
        at = (beat_at(beat.get("at")) if beat else None) or known_last_beat
        return GatewayStatus(name, QUARANTINED, at, beat or {}, quarantined=quarantined["since"],
                             quarantine_reason=quarantined["reason"])
    if error:
        return GatewayStatus(name, UNREACHABLE, known_last_beat, redis_error=error)
    at = None if beat is None else beat_at(beat.get("at"))
    if beat is None or at is None:  # a beat without a plausible time is no sign of life
        return GatewayStatus(name, OFFLINE if known_last_beat else NEVER, known_last_beat)
    if beat.get("stopped"):
        return GatewayStatus(name, STOPPED, at, beat)
    fresh = time.time() - at.timestamp() <= settings.LIFECYCLE["GATEWAY_OFFLINE_AFTER"]
    if fresh and presence.process_gone(redis_client(), str(beat.get("client") or ""), read_at):
        return GatewayStatus(name, OFFLINE, at, beat, ended=True)
    return GatewayStatus(name, ONLINE if fresh else OFFLINE, at, beat)


def status(gateway: Gateway | str) -> GatewayStatus:
    """A gateway's status from its heartbeat (read at most once per BEAT_CACHE_S)."""
    return statuses([gateway])[0]


def statuses(gateways: Iterable[Gateway | str]) -> list[GatewayStatus]:
    """The status of each gateway (names or rows; a row adds when it was last heard of,
    should its heartbeat key be gone), in one Redis round trip at most."""
    gateways = list(gateways)
    names = [g.name if isinstance(g, Gateway) else g for g in gateways]
    beats = read_beats(names)
    with _beats_lock:
        read_at = {n: _beats[n][0] if n in _beats else time.monotonic() for n in names}
    return [
        _status(name, *beats[name], gateway.last_beat if isinstance(gateway, Gateway) else None, read_at[name])
        for name, gateway in zip(names, gateways, strict=True)
    ]


def dds_summary(dds: dict) -> str:
    """'SUBNET · peers 10.0.0.5;10.0.0.6' from the discovery settings a gateway reports."""
    if not dds:
        return ""
    parts = []
    if dds.get("ROS_AUTOMATIC_DISCOVERY_RANGE"):
        parts.append(_("discovery %(range)s") % {"range": dds["ROS_AUTOMATIC_DISCOVERY_RANGE"]})
    if dds.get("ROS_STATIC_PEERS"):
        parts.append(_("peers %(peers)s") % {"peers": dds["ROS_STATIC_PEERS"]})
    if dds.get("ROS_DISCOVERY_SERVER"):
        parts.append(_("discovery server %(server)s") % {"server": dds["ROS_DISCOVERY_SERVER"]})
    if dds.get("ROS_SUPER_CLIENT"):
        parts.append(_("super client"))
    if dds.get("LIFECYCLE_DDS_INTERFACES"):
        parts.append(_("interfaces %(interfaces)s") % {"interfaces": dds["LIFECYCLE_DDS_INTERFACES"]})
    if dds.get("RMW_IMPLEMENTATION"):
        parts.append(dds["RMW_IMPLEMENTATION"])
    return " · ".join(parts)


def _started(beat: dict, gateway: Gateway) -> str | None:
    started = beat_started(beat.get("started")) if "started" in beat else plausible(gateway.started)
    return started.isoformat() if started else None


def describe(gateway: Gateway, state: GatewayStatus, robots: list[str] | None = None) -> dict:
    """A gateway as pages and the API show it: its status, what it reports (its heartbeat,
    else what the ingest process last copied) and the site's accounts of its streams."""
    beat = state.beat
    outbox = beat.get("outbox") if isinstance(beat.get("outbox"), dict) else gateway.outbox or {}
    dds = beat.get("dds") if isinstance(beat.get("dds"), dict) else gateway.dds or {}
    return {
        **state.as_dict(),
        "description": gateway.description,
        "since": "" if state.online or state.last_beat is None else _when(state.last_beat),
        "version": str(beat.get("version") or gateway.version),
        "host": str(beat.get("host") or gateway.host),
        "pid": beat.get("pid") or gateway.pid,
        "started": _started(beat, gateway),
        "domains": beat.get("domains") if isinstance(beat.get("domains"), list) else gateway.domains,
        "dds": dds,
        "dds_summary": dds_summary(dds),
        "nodes": beat.get("nodes") if isinstance(beat.get("nodes"), int) else gateway.node_count,
        "backlog": gateway.backlog,
        "facts_lost": gateway.facts_lost,
        "facts_rejected": gateway.facts_rejected,
        "live_refused": gateway.live_refused,
        "quarantines": gateway.quarantines,
        "redis_bytes": gateway.redis_bytes,
        "logs_lost": gateway.logs_lost,
        "logs_dropped": gateway.logs_dropped,
        "outbox": outbox,
        "outbox_dropped": int(outbox.get("facts_dropped") or 0) + int(outbox.get("logs_dropped") or 0),
        "robots": robots if robots is not None else [],
    }
