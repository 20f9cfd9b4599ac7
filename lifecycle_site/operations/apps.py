from django.apps import AppConfig


class OperationsConfig(AppConfig):
    name = "lifecycle_site.operations"
    verbose_name = "Operations"
