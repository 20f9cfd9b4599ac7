import redis
from django import forms
from django.contrib import admin, messages
from django.db.models import Count
from django.urls import reverse
from django.utils.html import format_html

from lifecycle_site.fleet import (
    accounts_admin,  # noqa: F401  (users and groups, limited by role)
    gateways,
    process_admin,  # noqa: F401  (launch profiles)
    quarantine,
)
from lifecycle_site.fleet.models import Gateway, ManagedNode, NodeAbsence, Robot


def dashboard_url(node: ManagedNode) -> str:
    return reverse("dashboard:node", args=[node.key])


class ManagedNodeInlineForm(forms.ModelForm):
    """A node found on the robot keeps its ROS name (its key, audit records and logs are by
    name); only a node added here, to be watched for, gets one typed in."""

    class Meta:
        model = ManagedNode
        fields = ("order", "name", "desired_state")

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        if self.instance.pk is not None:
            self.fields["name"].disabled = True
            self.fields["name"].help_text = ""


class ManagedNodeInline(admin.TabularInline):
    """The robot's nodes in bring-up order; 'order' and 'desired state' are edited here."""

    model = ManagedNode
    form = ManagedNodeInlineForm
    fields = ("order", "name", "desired_state", "state_label", "alive", "last_seen", "dashboard")
    readonly_fields = ("state_label", "alive", "last_seen", "dashboard")
    ordering = ("order", "name")
    extra = 0

    @admin.display(description="dashboard")
    def dashboard(self, obj: ManagedNode) -> str:
        return format_html('<a href="{}">node page</a>', dashboard_url(obj)) if obj.pk and obj.key else ""


@admin.register(Robot)
class RobotAdmin(admin.ModelAdmin):
    list_display = ("name", "gateway", "domain_id", "namespace", "enabled", "auto_recover", "created")
    list_filter = ("gateway", "enabled", "auto_recover", "domain_id")
    list_select_related = ("gateway",)
    search_fields = ("name", "description")
    inlines = [ManagedNodeInline]

    def view_on_site(self, obj: Robot) -> str:
        """The admin's "View on site" button opens the fleet page filtered to this robot."""
        return f"{reverse('dashboard:fleet')}?robot={obj.name}"


class NodeAbsenceInline(admin.TabularInline):
    """When the node was away (read-only: the ingest process writes these from the gateway's reports)."""

    model = NodeAbsence
    fields = ("gone_at", "back_at", "reason")
    readonly_fields = fields
    extra = 0
    max_num = 0
    can_delete = False
    ordering = ("-gone_at",)
    verbose_name_plural = "absences (newest first; the timeline page draws them)"

    def get_queryset(self, request):
        # A flapping node may have thousands: the newest 20 of the node shown are listed.
        node_id = (request.resolver_match.kwargs if request.resolver_match else {}).get("object_id")
        newest = NodeAbsence.objects.filter(node_id=node_id).order_by("-gone_at").values("pk")[:20]
        return super().get_queryset(request).filter(pk__in=newest)


@admin.register(ManagedNode)
class ManagedNodeAdmin(admin.ModelAdmin):
    list_display = ("name", "robot", "order", "state_label", "desired_state", "alive", "last_seen", "dashboard")
    list_filter = ("robot", "alive", "state_label")
    search_fields = ("name",)
    readonly_fields = ("key", "state_id", "state_label", "alive", "first_seen", "last_seen", "state_changed")
    inlines = [NodeAbsenceInline]

    def get_readonly_fields(self, request, obj=None):
        # A node's robot and ROS name are what it is: changing them would make it another node.
        return ("robot", "name", *self.readonly_fields) if obj is not None else self.readonly_fields

    def view_on_site(self, obj: ManagedNode) -> str:
        """The admin's "View on site" button opens the node's dashboard page."""
        return dashboard_url(obj)

    @admin.display(description="dashboard")
    def dashboard(self, obj: ManagedNode) -> str:
        return format_html('<a href="{}">node page</a>', dashboard_url(obj))


class RobotInline(admin.TabularInline):
    model = Robot
    fields = ("name", "domain_id", "namespace", "enabled")
    readonly_fields = fields
    extra = 0
    can_delete = False
    show_change_link = True

    def has_add_permission(self, request, obj=None) -> bool:
        return False


@admin.register(Gateway)
class GatewayAdmin(admin.ModelAdmin):
    """Gateways report what they are; the site keeps the accounts of their streams. Neither is
    edited here, and the Redis password is never shown (``manage.py add_gateway`` issues it)."""

    list_display = ("name", "online", "last_beat", "version", "host", "robot_count", "backlog", "lost")
    search_fields = ("name", "description", "host")
    reported = ("last_beat", "started", "stopped", "instance", "version", "host", "pid", "domains", "dds",
                "node_count", "outbox")
    accounts = ("backlog", "facts_lost", "facts_rejected", "live_refused", "logs_lost", "logs_dropped",
                "facts_cursor", "logs_cursor")
    trust = ("quarantined", "quarantine_reason", "quarantines", "redis_bytes")
    readonly_fields = ("status", "credentials", "created", *reported, *accounts, *trust)
    fieldsets = (
        (None, {"fields": ("name", "description", "status", "credentials", "created")}),
        ("Quarantine (the site cuts off a gateway that breaks the rules)", {"fields": trust}),
        ("What it reports (its heartbeat)", {"fields": reported}),
        ("What the site stored of its streams", {"fields": accounts}),
    )
    inlines = [RobotInline]
    actions = ["lift_quarantine"]

    @admin.action(description="Lift the quarantine of the selected gateways (deal with its cause first)")
    def lift_quarantine(self, request, queryset) -> None:
        lifted = []
        for gateway in queryset.filter(quarantined__isnull=False):
            try:
                quarantine.lift(gateway)
            except redis.RedisError as exc:
                self.message_user(request, f"Redis did not answer ({exc}); nothing was lifted.", messages.ERROR)
                return
            lifted.append(gateway.name)
        if lifted:
            self.message_user(request, f"Lifted the quarantine of {', '.join(lifted)}: the site reads what they send "
                              "again. If the device may have been tampered with, give it new credentials "
                              "(manage.py add_gateway NAME --env-file FILE).", messages.SUCCESS)
        else:
            self.message_user(request, "None of the selected gateways is quarantined.", messages.INFO)

    def get_queryset(self, request):
        return super().get_queryset(request).annotate(robots_total=Count("robots"))

    def get_readonly_fields(self, request, obj=None):
        return ("name", *self.readonly_fields) if obj is not None else self.readonly_fields

    @admin.display(boolean=True)
    def online(self, obj: Gateway) -> bool:
        return gateways.status(obj).online

    @admin.display(description="status")
    def status(self, obj: Gateway) -> str:
        state = gateways.status(obj)
        return "online" if state.online else state.reason()

    @admin.display(description="Redis credentials")
    def credentials(self, obj: Gateway) -> str:
        if obj.redis_password_sha256:
            return f"Redis user {obj.redis_user}. New password: manage.py add_gateway {obj.name} --env-file FILE"
        return f"none yet (the default Redis user). Issue them: manage.py add_gateway {obj.name} --env-file FILE"

    @admin.display(description="robots", ordering="robots_total")
    def robot_count(self, obj: Gateway) -> int:
        return obj.robots_total

    @admin.display(description="lost / dropped")
    def lost(self, obj: Gateway) -> str:
        return (f"{obj.facts_lost} facts, {obj.logs_lost} log batches, {obj.logs_dropped} log lines"
                + (f", {obj.facts_rejected} facts rejected" if obj.facts_rejected else ""))
