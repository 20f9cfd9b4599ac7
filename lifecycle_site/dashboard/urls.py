from django.urls import path

from lifecycle_site.dashboard import audit_views, log_views, views

app_name = "dashboard"
urlpatterns = [
    path("", views.fleet, name="fleet"),
    path("nodes/<str:key>/", views.node_detail, name="node"),
    path("nodes/<str:key>/transition", views.node_transition, name="node-transition"),
    path("robots/<str:robot>/watch", views.watch_node, name="watch-node"),
    path("logs/<str:scope>/<str:name>/", log_views.log_console, name="logs"),
    path("logs/<str:scope>/<str:name>/download", log_views.log_download, name="logs-download"),
    path("logs/<str:scope>/<str:name>/since", log_views.log_since, name="logs-since"),
    path("audit/", audit_views.audit_list, name="audit"),
    path("audit.csv", audit_views.audit_csv, name="audit-csv"),
]
