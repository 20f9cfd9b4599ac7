from django.apps import AppConfig
from django.utils.translation import gettext_lazy


class ModesConfig(AppConfig):
    name = "lifecycle_site.modes"
    verbose_name = gettext_lazy("Robot modes")
