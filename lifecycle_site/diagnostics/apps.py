from django.apps import AppConfig


class DiagnosticsConfig(AppConfig):
    name = "lifecycle_site.diagnostics"
    verbose_name = "Robot diagnostics"
