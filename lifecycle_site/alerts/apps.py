from django.apps import AppConfig


class AlertsConfig(AppConfig):
    name = "lifecycle_site.alerts"
    verbose_name = "Alerts"

    def ready(self) -> None:
        # The ingest process hands the rules what it stores (ingest/watchers.py).
        from lifecycle_site.alerts.engine import Evaluator
        from lifecycle_site.ingest import watchers

        watchers.register(Evaluator)
