from django.apps import AppConfig


class ModesConfig(AppConfig):
    name = "lifecycle_site.modes"
    verbose_name = "Robot modes"
