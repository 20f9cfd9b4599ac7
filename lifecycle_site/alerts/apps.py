from django.apps import AppConfig
from django.db.models.signals import post_migrate
from django.utils.translation import gettext_lazy


class AlertsConfig(AppConfig):
    name = "lifecycle_site.alerts"
    verbose_name = gettext_lazy("Alerts")

    def ready(self) -> None:
        # The ingest process hands the rules what it stores (ingest/watchers.py).
        from lifecycle_site.alerts.engine import Evaluator
        from lifecycle_site.ingest import watchers

        watchers.register(Evaluator)
        from lifecycle_site.alerts.installed_rules import ensure_installed_rules

        post_migrate.connect(ensure_installed_rules, sender=self, dispatch_uid="alerts.installed_rules")
