from django.contrib import admin

from lifecycle_site.sign_in.models import DirectoryAccount


@admin.register(DirectoryAccount)
class DirectoryAccountAdmin(admin.ModelAdmin):
    """Read only: the directory decides; switch an account off on its user instead."""

    list_display = ("user", "source", "role", "last_sign_in", "confirmed")
    list_filter = ("source", "role")
    search_fields = ("user__username", "subject")
    readonly_fields = ("user", "source", "subject", "role", "groups", "last_sign_in", "confirmed")

    def has_add_permission(self, request) -> bool:
        return False

    def has_change_permission(self, request, obj=None) -> bool:
        return False
