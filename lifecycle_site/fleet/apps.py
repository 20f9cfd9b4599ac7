from django.apps import AppConfig


class FleetConfig(AppConfig):
    name = "lifecycle_site.fleet"
    verbose_name = "Fleet"

    def ready(self) -> None:
        from django.db.models.signals import post_migrate

        from lifecycle_site.fleet.roles import ensure_roles

        post_migrate.connect(ensure_roles, sender=self)
