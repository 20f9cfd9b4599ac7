from django.apps import AppConfig


class ApiConfig(AppConfig):
    name = "lifecycle_site.api"
    verbose_name = "JSON API"

    def ready(self) -> None:
        from lifecycle_site.api import grants

        grants.connect_invalidation()
