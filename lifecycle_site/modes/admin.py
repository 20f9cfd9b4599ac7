"""The admin's pages for robot modes (admins define them; operators apply them from the robot page,
the API or the command line) and, read-only, which mode each robot is in."""
from __future__ import annotations

from django.contrib import admin
from django.utils.translation import gettext_lazy

from lifecycle_site.modes.models import CurrentMode, Mode


@admin.register(Mode)
class ModeAdmin(admin.ModelAdmin):
    list_display = ("name", "robot_names", "node_count", "updated")
    search_fields = ("name", "description")
    filter_horizontal = ("robots",)
    fields = ("name", "description", "robots", "nodes")

    @admin.display(description=gettext_lazy("robots"))
    def robot_names(self, mode: Mode) -> str:
        return ", ".join(mode.robots.values_list("name", flat=True)) or "-"

    @admin.display(description=gettext_lazy("nodes"))
    def node_count(self, mode: Mode) -> int:
        return len(mode.nodes)

    def save_model(self, request, obj: Mode, form, change: bool) -> None:
        obj.updated_by = request.user
        super().save_model(request, obj, form, change)


@admin.register(CurrentMode)
class CurrentModeAdmin(admin.ModelAdmin):
    list_display = ("robot", "mode", "since", "applied_by")
    readonly_fields = ("robot", "mode", "since", "applied_by", "run")

    def has_add_permission(self, request) -> bool:
        return False

    def has_change_permission(self, request, obj=None) -> bool:
        return False
