from django.urls import path, re_path

from lifecycle_site.api import views
from lifecycle_site.api.auth import not_found

app_name = "api"
urlpatterns = [
    path("robots", views.robots, name="robots"),
    path("nodes", views.nodes, name="nodes"),
    path("nodes/<str:key>", views.node_detail, name="node"),
    path("nodes/<str:key>/transition", views.transition, name="transition"),
    path("nodes/<str:key>/logs", views.node_logs, name="node-logs"),
    path("transitions", views.transitions, name="transitions"),
    re_path(r"^(?P<path>.*)$", not_found),
]
