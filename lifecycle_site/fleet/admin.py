from django.contrib import admin

from lifecycle_site.fleet.models import ManagedNode, Robot


class ManagedNodeInline(admin.TabularInline):
    model = ManagedNode
    fields = ("name", "state_label", "alive", "last_seen")
    readonly_fields = ("state_label", "alive", "last_seen")
    extra = 0


@admin.register(Robot)
class RobotAdmin(admin.ModelAdmin):
    list_display = ("name", "domain_id", "namespace", "enabled", "created")
    list_filter = ("enabled", "domain_id")
    search_fields = ("name", "description")
    inlines = [ManagedNodeInline]


@admin.register(ManagedNode)
class ManagedNodeAdmin(admin.ModelAdmin):
    list_display = ("name", "robot", "state_label", "alive", "last_seen")
    list_filter = ("robot", "alive", "state_label")
    search_fields = ("name",)
    readonly_fields = ("key", "state_id", "state_label", "alive", "first_seen", "last_seen", "state_changed")
