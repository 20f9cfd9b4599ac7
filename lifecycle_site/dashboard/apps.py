from django.apps import AppConfig


class DashboardConfig(AppConfig):
    name = "lifecycle_site.dashboard"
    verbose_name = "Dashboard"
