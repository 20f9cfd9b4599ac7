"""Endpoints for orchestrators and plant monitoring (docs/monitoring.md):

- ``/healthz``: the process answers (liveness; nothing else is asked).
- ``/readyz``: the database and Redis answer, and Redis is not full (503 if not); the ingest
  processes (running, stalled, not running) and the gateways are reported beside them, as
  counts (no names: it needs no login); "degraded" when one of those is not as it should be.
- ``/metrics``: Prometheus text format, for an API token of any role, or without one from the
  addresses in LIFECYCLE_METRICS_ALLOW.
"""
from __future__ import annotations

import ipaddress
import time

import redis
from django.conf import settings
from django.db import DatabaseError, connection
from django.http import HttpRequest, HttpResponse, JsonResponse
from django.views.decorators.cache import never_cache
from django.views.decorators.http import require_GET
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest

from lifecycle_site.api.auth import api_view
from lifecycle_site.fleet.models import Gateway
from lifecycle_site.gateway_link import gateways
from lifecycle_site.ingest import shares
from lifecycle_site.monitoring.metrics import FleetCollector

READY_TIMEOUT_S = 2.0  # each dependency's answer, so a probe never hangs on a frozen Redis


@require_GET
@never_cache
def healthz(request: HttpRequest) -> JsonResponse:
    return JsonResponse({"status": "ok"})


def _database() -> str | None:
    try:
        with connection.cursor() as cursor:
            cursor.execute("SELECT 1")
    except DatabaseError as exc:
        return f"{type(exc).__name__}: {exc}"
    return None


# An ingest process reports each turn of its loop (ingest/shares.py); one whose last turn is
# older than this is stalled (frozen, hung on the database, or stopped without a word).
INGEST_STALLED_S = 10.0


def _redis() -> tuple[str | None, dict]:
    """(problem or None, what the ingest processes last said: {"state", ...})."""
    client = redis.Redis.from_url(settings.REDIS_URL, socket_connect_timeout=READY_TIMEOUT_S,
                                  socket_timeout=READY_TIMEOUT_S)
    try:
        client.ping()
        memory = client.info("memory")
        used, limit = int(memory.get("used_memory") or 0), int(memory.get("maxmemory") or 0)
        if limit and used >= limit:
            return f"Redis is full ({used:,} of its {limit:,} bytes): it refuses writes", {"state": "unknown"}
        return None, _ingest(shares.turns(client, gateways.channel_prefix()))
    except redis.RedisError as exc:
        return f"{type(exc).__name__}: {exc}", {"state": "unknown"}
    finally:
        client.close()


def _ingest(turns: list[dict]) -> dict:
    if not turns:
        return {"state": "not running"}
    age = time.time() - turns[0]["at"]
    if age > INGEST_STALLED_S:
        return {"state": "stalled", "last_turn_seconds_ago": round(age, 1),
                "problem": f"no ingest process has finished a turn for {age:.0f} s: facts and logs of the gateways "
                           "are not stored, alerts not evaluated"}
    fresh = [t for t in turns if time.time() - t["at"] <= INGEST_STALLED_S]
    return {"state": "running", "processes": len(fresh)}


@require_GET
@never_cache
def readyz(request: HttpRequest) -> JsonResponse:
    database = _database()
    link, ingest = _redis()
    body: dict = {
        "database": "ok" if database is None else "unavailable",
        "redis": "ok" if link is None else "unavailable",
        "ingest": ingest["state"],
    }
    if link and "full" in link:
        body["redis_problem"] = link
    if ingest.get("problem"):
        body["ingest_problem"] = ingest["problem"]
    if database is None:
        rows = list(Gateway.objects.filter(robots__isnull=False).distinct())
        states = gateways.statuses(rows) if link is None else []
        body["gateways"] = {"with_robots": len(rows), "online": sum(1 for s in states if s.online),
                            "quarantined": sum(1 for s in states if s.state == gateways.QUARANTINED)}
    ready = database is None and link is None
    degraded = ingest["state"] != "running" or \
        body.get("gateways", {}).get("online") != body.get("gateways", {}).get("with_robots")
    body["status"] = "unavailable" if not ready else "degraded" if degraded else "ready"
    return JsonResponse(body, status=200 if ready else 503)


def _allowed(address: str) -> bool:
    try:
        client = ipaddress.ip_address(address)
    except ValueError:
        return False
    return any(client in network for network in settings.LIFECYCLE_METRICS_ALLOW)


def _exposition() -> HttpResponse:
    registry = CollectorRegistry(auto_describe=False)
    registry.register(FleetCollector())
    return HttpResponse(generate_latest(registry), content_type=CONTENT_TYPE_LATEST)


@api_view()
def _metrics_for_token(request: HttpRequest) -> HttpResponse:
    return _exposition()


@never_cache
def metrics(request: HttpRequest) -> HttpResponse:
    if request.method == "GET" and "Authorization" not in request.headers and _allowed(
            request.META.get("REMOTE_ADDR", "")):
        return _exposition()
    return _metrics_for_token(request)
