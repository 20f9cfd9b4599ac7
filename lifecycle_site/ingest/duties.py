"""What the site owes its gateways, done by the one ingest process that holds the site's lease:
their heartbeats and backlogs copied into their rows, their configs published, their Redis users
kept in place (quarantines included), and the rows and Redis agreeing on who is quarantined."""
from __future__ import annotations

import logging
import time
from typing import Any

import redis
from django.utils import timezone

from lifecycle_site.fleet.models import Gateway
from lifecycle_site.gateway_link import gateway_config, quarantine, redis_users
from lifecycle_site.gateway_link import gateways as gw
from lifecycle_site.gateway_link.stream_entries import beat_fields, text
from lifecycle_site.ingest import outages
from ros_gateway.shared import protocol

log = logging.getLogger(__name__)

CONFIG_EVERY_S = 60.0  # publish configs even when unchanged


class SiteDuties:
    def __init__(self, client: redis.Redis, prefix: str) -> None:
        self.redis, self.prefix = client, prefix
        self.published: dict[str, tuple[str, float]] = {}  # gateway -> (config version, when)

    def forget(self) -> None:
        """Redis failed: it may have restarted without its data (configs, users)."""
        self.published.clear()

    def copy_beats(self, names: list[str]) -> None:
        """Each gateway's heartbeat and stream backlog into its row (for pages and the API), and
        its outages opened or closed (for the state timeline)."""
        if not names:
            return
        beats = self.redis.mget([protocol.beat_key(self.prefix, n) for n in names])
        backlogs = self.backlogs(names)
        rows = {row.name: row for row in Gateway.objects.filter(name__in=names).only("name", "instance", "last_beat")}
        for name, raw in zip(names, beats, strict=True):
            changes: dict[str, Any] = {"backlog": backlogs.get(name, 0)}
            beat = gw._parse_beat(raw)
            if beat is not None:
                if name in rows:  # a new process: the stretch since the last one's last beat
                    outages.note_restart(rows[name], beat)
                changes.update(beat_fields(beat))
            Gateway.objects.filter(name=name).update(**changes)
        outages.observe(Gateway.objects.filter(name__in=names))

    def backlogs(self, names: list[str]) -> dict[str, int]:
        """Entries not yet stored, per gateway: the group's lag (Redis 7) or an estimate, plus
        what was delivered and not acknowledged."""
        streams = [(n, s) for n in names for s in (protocol.facts_stream(self.prefix, n),
                                                   protocol.logs_stream(self.prefix, n))]
        pipe = self.redis.pipeline(transaction=False)
        for _, stream in streams:
            pipe.xinfo_groups(stream)
        totals: dict[str, int] = {}
        for (name, stream), groups in zip(streams, pipe.execute(raise_on_error=False), strict=True):
            if isinstance(groups, Exception):
                continue
            for group in groups:
                if group.get("name") not in (protocol.INGEST_GROUP, protocol.INGEST_GROUP.encode()):
                    continue
                lag = group.get("lag")
                if lag is None:
                    last = text(group.get("last-delivered-id") or b"0-0")
                    lag = len(self.redis.xrange(stream, f"({last}", "+", count=10_000))
                totals[name] = totals.get(name, 0) + int(lag) + int(group.get("pending") or 0)
        return totals

    def publish_configs(self, names: list[str]) -> None:
        """Each gateway's config when it changed (its quota included), and at least every
        CONFIG_EVERY_S."""
        now = time.monotonic()
        for name in names:
            config = gateway_config.build_config(name)
            version, when = self.published.get(name, ("", 0.0))
            if config["version"] != version or now - when >= CONFIG_EVERY_S:
                self.redis.set(protocol.config_key(self.prefix, name), protocol.encode(config))
                self.published[name] = (config["version"], now)

    def keep_users(self) -> None:
        """Re-create gateways' Redis users that Redis lost (a restart without persistence), and
        keep a quarantined one's user disabled."""
        quarantine.keep_records(self.redis)
        held = quarantine.current(self.redis)  # (a quarantine under way is in Redis before its row)
        for row in Gateway.objects.exclude(redis_password_sha256=""):
            if row.quarantined is None and row.name in held:
                row.quarantined = held[row.name]["since"] or timezone.now()
            if not redis_users.user_is_current(row, self.redis):
                redis_users.apply_user(row, self.redis)
                log.info("re-created the Redis user %s of gateway %s", row.redis_user, row.name)
