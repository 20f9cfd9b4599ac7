from django.apps import AppConfig
from django.utils.translation import gettext_lazy as _


class DashboardConfig(AppConfig):
    name = "lifecycle_site.dashboard"
    verbose_name = _("Dashboard")
