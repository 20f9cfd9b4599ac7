from django.apps import AppConfig


class AlertsConfig(AppConfig):
    name = "lifecycle_site.alerts"
    verbose_name = "Alerts"
