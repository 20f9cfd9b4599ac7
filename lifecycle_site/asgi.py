"""ASGI entry point: Django views over HTTP, Channels consumers over WebSocket."""
import os

import django

os.environ.setdefault("DJANGO_SETTINGS_MODULE", "lifecycle_site.settings")

django.setup(set_prefix=False)

from lifecycle_site.http_handler import SyncChainHandler  # noqa: E402  (needs Django set up first)

django_asgi_app = SyncChainHandler()

from channels.auth import AuthMiddlewareStack  # noqa: E402  (needs Django set up first)
from channels.routing import ProtocolTypeRouter, URLRouter  # noqa: E402

from lifecycle_site.dashboard.routing import websocket_urlpatterns  # noqa: E402
from lifecycle_site.socket_origin import SameOriginValidator  # noqa: E402

application = ProtocolTypeRouter(
    {
        "http": django_asgi_app,
        # Sockets of the site's own pages only (Origin = scheme, host and port the socket was opened on).
        "websocket": AuthMiddlewareStack(SameOriginValidator(URLRouter(websocket_urlpatterns))),
    }
)
