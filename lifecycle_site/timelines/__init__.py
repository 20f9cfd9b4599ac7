"""State timelines of nodes and robots, computed from the audit log and absences: read by the pages
(dashboard/timeline_views.py) and the API (api/timeline.py)."""
