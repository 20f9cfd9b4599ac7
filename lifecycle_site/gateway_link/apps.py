from django.apps import AppConfig
from django.utils.translation import gettext_lazy


class GatewayLinkConfig(AppConfig):
    """The site's link to its gateways: commands and their replies, heartbeats, configs, Redis users
    and quotas, quarantines, and the checks of everything a gateway sends."""

    name = "lifecycle_site.gateway_link"
    verbose_name = gettext_lazy("Gateway link")

    def ready(self) -> None:
        from lifecycle_site.gateway_link import (  # noqa: F401
            gateway_config,  # its signals publish configs
            redis_users,  # its signal drops a deleted gateway's user
        )
