"""Server-rendered pages of the dashboard."""
from __future__ import annotations

from django.contrib.auth.decorators import login_required
from django.http import HttpRequest, HttpResponse
from django.shortcuts import render

from lifecycle_site.fleet.models import GatewayHeartbeat, Robot


@login_required
def fleet(request: HttpRequest) -> HttpResponse:
    robots = Robot.objects.prefetch_related("nodes").order_by("name")
    return render(
        request,
        "dashboard/fleet.html",
        {"robots": robots, "gateway_online": GatewayHeartbeat.online()},
    )
