from django.contrib import admin

from lifecycle_site.audit.models import AccessDenial, ParameterRecord, TransitionRecord


class ReadOnlyAdmin(admin.ModelAdmin):
    """Records that can be browsed, never added, changed or deleted in the admin (audit records,
    token events, alerts and their deliveries)."""

    def has_add_permission(self, request) -> bool:
        return False

    def has_change_permission(self, request, obj=None) -> bool:
        return False

    def has_delete_permission(self, request, obj=None) -> bool:
        return False


@admin.register(TransitionRecord)
class TransitionRecordAdmin(ReadOnlyAdmin):
    """Read-only: the audit log is append-only."""

    list_display = (
        "requested_at", "robot_name", "node_name", "transition_label", "start_state_label",
        "result_state_label", "outcome", "source", "requested_by_name", "duration_ms",
    )
    list_filter = ("outcome", "source", "robot_name")
    search_fields = ("node_name", "requested_by_name", "error")
    date_hierarchy = "requested_at"


@admin.register(ParameterRecord)
class ParameterRecordAdmin(ReadOnlyAdmin):
    """Read-only: parameter changes are part of the append-only audit log."""

    list_display = ("at", "robot_name", "node_name", "name", "old_value", "new_value", "outcome", "source",
                    "requested_by_name")
    list_filter = ("outcome", "source", "robot_name")
    search_fields = ("node_name", "name", "requested_by_name", "reason")
    date_hierarchy = "at"


@admin.register(AccessDenial)
class AccessDenialAdmin(ReadOnlyAdmin):
    """Refused attempts (the newest 10,000): who, from where, what, why."""

    list_display = ("at", "code", "status", "username", "client", "method", "path", "detail")
    list_filter = ("code", "status")
    search_fields = ("username", "client", "path")
    date_hierarchy = "at"
