from django.apps import AppConfig


class AuditConfig(AppConfig):
    name = "lifecycle_site.audit"
    verbose_name = "Audit history"
