from django.contrib import admin

from lifecycle_site.fleet import accounts_admin  # noqa: F401  (users and groups, limited by role)
from lifecycle_site.fleet.models import ManagedNode, Robot


class ManagedNodeInline(admin.TabularInline):
    """The robot's nodes in bring-up order; 'order' and 'desired state' are edited here."""

    model = ManagedNode
    fields = ("order", "name", "desired_state", "state_label", "alive", "last_seen")
    readonly_fields = ("state_label", "alive", "last_seen")
    ordering = ("order", "name")
    extra = 0


@admin.register(Robot)
class RobotAdmin(admin.ModelAdmin):
    list_display = ("name", "domain_id", "namespace", "enabled", "auto_recover", "created")
    list_filter = ("enabled", "auto_recover", "domain_id")
    search_fields = ("name", "description")
    inlines = [ManagedNodeInline]


@admin.register(ManagedNode)
class ManagedNodeAdmin(admin.ModelAdmin):
    list_display = ("name", "robot", "order", "state_label", "desired_state", "alive", "last_seen")
    list_filter = ("robot", "alive", "state_label")
    search_fields = ("name",)
    readonly_fields = ("key", "state_id", "state_label", "alive", "first_seen", "last_seen", "state_changed")
