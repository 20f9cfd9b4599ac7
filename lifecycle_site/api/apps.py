from django.apps import AppConfig


class ApiConfig(AppConfig):
    name = "lifecycle_site.api"
    verbose_name = "JSON API"
