from django.http import HttpResponseRedirect
from django.templatetags.static import static
from django.urls import path

from lifecycle_site.dashboard import (
    audit_views,
    diagnostic_views,
    log_views,
    mode_views,
    operation_views,
    parameter_views,
    process_views,
    timeline_views,
    token_views,
    views,
)

app_name = "dashboard"
urlpatterns = [
    path("", views.fleet, name="fleet"),
    path("nodes/<str:key>/", views.node_detail, name="node"),
    path("nodes/<str:key>/transition", views.node_transition, name="node-transition"),
    path("fleet/find", views.fleet_find, name="fleet-find"),
    path("robots/<str:robot>/nodes", views.robot_section, name="robot-section"),
    path("robots/<str:robot>/watch", views.watch_node, name="watch-node"),
    path("robots/<str:robot>/operations", operation_views.robot_operation, name="robot-operation"),
    path("robots/<str:robot>/processes/", process_views.robot_processes, name="robot-processes"),
    path("robots/<str:robot>/processes/rows", process_views.robot_processes_rows, name="robot-processes-rows"),
    path("robots/<str:robot>/processes/usage", process_views.robot_processes_usage, name="robot-processes-usage"),
    path("robots/<str:robot>/processes/<str:process>/<str:action>", process_views.process_action,
         name="process-action"),
    path("robots/<str:robot>/modes/", mode_views.robot_modes, name="robot-modes"),
    path("robots/<str:robot>/modes/import", mode_views.import_file, name="robot-modes-import"),
    path("robots/<str:robot>/modes/<str:mode>/apply", mode_views.apply, name="robot-mode-apply"),
    path("robots/<str:robot>/diagnostics/", diagnostic_views.robot_diagnostics, name="robot-diagnostics"),
    path("robots/<str:robot>/diagnostics/status", diagnostic_views.status_detail, name="robot-diagnostic"),
    path("robots/<str:robot>/diagnostics/forget-stale", diagnostic_views.forget_stale,
         name="robot-diagnostics-forget-stale"),
    path("nodes/<str:key>/restart", operation_views.node_restart, name="node-restart"),
    path("nodes/<str:key>/desired-state", operation_views.desired_state, name="node-desired-state"),
    path("nodes/<str:key>/parameters", parameter_views.parameters, name="node-parameters"),
    path("nodes/<str:key>/parameters/import", parameter_views.import_file, name="node-parameters-import"),
    path("nodes/<str:key>/parameters/apply", parameter_views.apply_file, name="node-parameters-apply"),
    path("logs/<str:scope>/<str:name>/", log_views.log_console, name="logs"),
    path("logs/<str:scope>/<str:name>/download", log_views.log_download, name="logs-download"),
    path("logs/<str:scope>/<str:name>/since", log_views.log_since, name="logs-since"),
    path("nodes/<str:key>/timeline/", timeline_views.node_timeline, name="node-timeline"),
    path("robots/<str:robot>/timeline/", timeline_views.robot_timeline, name="robot-timeline"),
    path("audit/", audit_views.audit_list, name="audit"),
    path("audit.csv", audit_views.audit_csv, name="audit-csv"),
    # Browsers ask for /favicon.ico where a page names no icon (JSON, text, the 404 page).
    path("favicon.ico", lambda request: HttpResponseRedirect(static("img/favicon.svg")), name="favicon"),
    path("tokens/", token_views.my_tokens, name="tokens"),
    path("tokens/<int:token_id>/revoke", token_views.revoke_token, name="token-revoke"),
]
