from django.contrib import admin

from lifecycle_site.api.models import ApiToken


@admin.register(ApiToken)
class ApiTokenAdmin(admin.ModelAdmin):
    """Tokens are issued with ``manage.py create_api_token``; here they can be reviewed and revoked."""

    list_display = ("hint", "user", "name", "created", "last_used")
    readonly_fields = ("user", "name", "hint", "created", "last_used")

    def has_add_permission(self, request) -> bool:
        return False
