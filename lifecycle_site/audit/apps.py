from django.apps import AppConfig


class AuditConfig(AppConfig):
    name = "lifecycle_site.audit"
    verbose_name = "Audit history"

    def ready(self) -> None:
        from lifecycle_site.audit import denials  # noqa: F401  (connects the failed-login signal)
