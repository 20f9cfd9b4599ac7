from django.apps import AppConfig
from django.utils.translation import gettext_lazy


class ApiConfig(AppConfig):
    name = "lifecycle_site.api"
    verbose_name = gettext_lazy("JSON API")

    def ready(self) -> None:
        from lifecycle_site.api import grants

        grants.connect_invalidation()
