"""WebSocket routes: live fragments for the fleet and node pages, JSON for log consoles."""
from django.urls import path

from lifecycle_site.dashboard import consumers, node_consumers
from lifecycle_site.dashboard.audit_consumer import AuditConsumer
from lifecycle_site.dashboard.diagnostic_consumer import DiagnosticsConsumer
from lifecycle_site.dashboard.mode_consumer import ModesConsumer

websocket_urlpatterns = [
    path("ws/fleet/", consumers.FleetConsumer.as_asgi()),
    path("ws/nodes/<str:key>/", node_consumers.NodeConsumer.as_asgi()),
    path("ws/logs/<str:scope>/<str:name>/", node_consumers.LogConsumer.as_asgi()),
    path("ws/audit/", AuditConsumer.as_asgi()),
    path("ws/robots/<str:robot>/modes/", ModesConsumer.as_asgi()),
    path("ws/robots/<str:robot>/diagnostics/", DiagnosticsConsumer.as_asgi()),
]
