"""WebSocket routes (live updates are added by the dashboard)."""
websocket_urlpatterns: list = []
