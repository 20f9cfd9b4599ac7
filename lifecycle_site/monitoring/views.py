"""Endpoints for orchestrators and plant monitoring (docs/monitoring.md):

- ``/healthz``: the process answers (liveness; nothing else is asked).
- ``/readyz``: the database and Redis answer (503 if not); the ingest process and the
  gateways are reported beside them, as counts (no names: it needs no login).
- ``/metrics``: Prometheus text format, for an API token of any role, or without one from the
  addresses in LIFECYCLE_METRICS_ALLOW.
"""
from __future__ import annotations

import ipaddress

import redis
from django.conf import settings
from django.db import DatabaseError, connection
from django.http import HttpRequest, HttpResponse, JsonResponse
from django.views.decorators.cache import never_cache
from django.views.decorators.http import require_GET
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest

from lifecycle_site.api.auth import api_view
from lifecycle_site.fleet import gateways
from lifecycle_site.fleet.models import Gateway
from lifecycle_site.monitoring.metrics import FleetCollector
from ros_gateway.shared import protocol

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


def _redis() -> tuple[str | None, bool]:
    """(problem or None, whether an ingest process holds its lease)."""
    client = redis.Redis.from_url(settings.REDIS_URL, socket_connect_timeout=READY_TIMEOUT_S,
                                  socket_timeout=READY_TIMEOUT_S)
    try:
        client.ping()
        return None, bool(client.exists(protocol.ingest_lease_key(gateways.channel_prefix())))
    except redis.RedisError as exc:
        return f"{type(exc).__name__}: {exc}", False
    finally:
        client.close()


@require_GET
@never_cache
def readyz(request: HttpRequest) -> JsonResponse:
    database = _database()
    link, ingesting = _redis()
    body: dict = {
        "database": "ok" if database is None else "unavailable",
        "redis": "ok" if link is None else "unavailable",
        "ingest": "running" if ingesting else "not running",
    }
    if database is None:
        rows = list(Gateway.objects.filter(robots__isnull=False).distinct())
        states = gateways.statuses(rows) if link is None else []
        body["gateways"] = {"with_robots": len(rows), "online": sum(1 for s in states if s.online)}
    ready = database is None and link is None
    degraded = not ingesting or body.get("gateways", {}).get("online") != body.get("gateways", {}).get("with_robots")
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
