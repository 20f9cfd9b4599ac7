from django.urls import path, re_path

from lifecycle_site.api import alerts, diagnostics, modes, operations, parameters, processes, timeline, views
from lifecycle_site.api.auth import not_found

app_name = "api"
urlpatterns = [
    path("gateways", views.gateways, name="gateways"),
    path("robots", views.robots, name="robots"),
    path("nodes", views.nodes, name="nodes"),
    path("nodes/<str:key>", views.node_detail, name="node"),
    path("nodes/<str:key>/transition", views.transition, name="transition"),
    path("nodes/<str:key>/logs", views.node_logs, name="node-logs"),
    path("transitions", views.transitions, name="transitions"),
    path("robots/<str:name>/operations", operations.robot_operation, name="robot-operation"),
    path("robots/<str:name>/runs", operations.robot_runs, name="robot-runs"),
    path("robots/<str:name>/processes", processes.robot_processes, name="robot-processes"),
    path("robots/<str:name>/processes/<str:process>", processes.process_action, name="process-action"),
    path("robots/<str:name>/modes", modes.robot_modes, name="robot-modes"),
    path("robots/<str:name>/modes.yaml", modes.robot_modes_yaml, name="robot-modes-yaml"),
    path("robots/<str:name>/modes/<str:mode>/apply", modes.apply, name="robot-mode-apply"),
    path("robots/<str:name>/drift", modes.robot_drift, name="robot-drift"),
    path("robots/<str:name>/diagnostics", diagnostics.robot_diagnostics, name="robot-diagnostics"),
    path("robots/<str:name>/diagnostics/history", diagnostics.status_history, name="robot-diagnostics-history"),
    path("modes", modes.modes, name="modes"),
    path("modes/import", modes.import_file, name="modes-import"),
    path("modes/<str:name>", modes.mode, name="mode"),
    path("runs/<str:run_id>", operations.run_detail, name="run"),
    path("nodes/<str:key>/restart", operations.node_restart, name="node-restart"),
    path("nodes/<str:key>/desired-state", operations.desired_state, name="node-desired-state"),
    path("nodes/<str:key>/parameters", parameters.node_parameters, name="node-parameters"),
    path("nodes/<str:key>/parameters.yaml", parameters.parameters_yaml, name="node-parameters-yaml"),
    path("nodes/<str:key>/timeline", timeline.node_timeline, name="node-timeline"),
    path("robots/<str:name>/timeline", timeline.robot_timeline, name="robot-timeline"),
    *alerts.urlpatterns,
    re_path(r"^(?P<path>.*)$", not_found),
]
