from django.apps import AppConfig
from django.utils.translation import gettext_lazy


class FleetConfig(AppConfig):
    name = "lifecycle_site.fleet"
    verbose_name = gettext_lazy("Fleet")

    def ready(self) -> None:
        from django.contrib.auth import get_user_model
        from django.db.models.signals import m2m_changed, post_migrate

        from lifecycle_site.fleet.roles import admins_are_staff, ensure_roles

        # After every app's migrations (not only ours): the roles use permissions of the audit and
        # api apps too, which exist only once those apps' post_migrate has run. Idempotent.
        post_migrate.connect(ensure_roles, dispatch_uid="fleet.ensure_roles")
        m2m_changed.connect(admins_are_staff, sender=get_user_model().groups.through)
