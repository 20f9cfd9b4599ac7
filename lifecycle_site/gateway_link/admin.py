"""The gateways in the admin: what each reports and what the site stored of its streams, its
quarantine (lifted here), its Redis credentials (issued by ``manage.py add_gateway``, never shown)."""
import redis
from django.contrib import admin, messages
from django.db.models import Count
from django.utils.translation import gettext as _
from django.utils.translation import gettext_lazy

from lifecycle_site.fleet.models import Gateway, Robot
from lifecycle_site.gateway_link import gateways, quarantine


class RobotInline(admin.TabularInline):
    model = Robot
    fields = ("name", "domain_id", "namespace", "enabled")
    readonly_fields = fields
    extra = 0
    can_delete = False
    show_change_link = True
    verbose_name = gettext_lazy("robot")  # (the model's own names, in English as before)
    verbose_name_plural = gettext_lazy("robots")

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
        (gettext_lazy("Quarantine (the site cuts off a gateway that breaks the rules)"), {"fields": trust}),
        (gettext_lazy("What it reports (its heartbeat)"), {"fields": reported}),
        (gettext_lazy("What the site stored of its streams"), {"fields": accounts}),
    )
    inlines = [RobotInline]
    actions = ["lift_quarantine"]

    @admin.action(description=gettext_lazy("Lift the quarantine of the selected gateways (deal with its cause first)"))
    def lift_quarantine(self, request, queryset) -> None:
        lifted = []
        for gateway in queryset.filter(quarantined__isnull=False):
            try:
                quarantine.lift(gateway)
            except redis.RedisError as exc:
                self.message_user(request, _("Redis did not answer (%(error)s); nothing was lifted.") % {"error": exc},
                                  messages.ERROR)
                return
            lifted.append(gateway.name)
        if lifted:
            self.message_user(request, _("Lifted the quarantine of %(gateways)s: the site reads what they send "
                                         "again. If the device may have been tampered with, give it new credentials "
                                         "(manage.py add_gateway NAME --env-file FILE).") % {
                                  "gateways": ", ".join(lifted)}, messages.SUCCESS)
        else:
            self.message_user(request, _("None of the selected gateways is quarantined."), messages.INFO)

    def get_queryset(self, request):
        return super().get_queryset(request).annotate(robots_total=Count("robots"))

    def get_readonly_fields(self, request, obj=None):
        return ("name", *self.readonly_fields) if obj is not None else self.readonly_fields

    @admin.display(boolean=True, description=gettext_lazy("online"))
    def online(self, obj: Gateway) -> bool:
        return gateways.status(obj).online

    @admin.display(description=gettext_lazy("status"))
    def status(self, obj: Gateway) -> str:
        state = gateways.status(obj)
        return _("online") if state.online else state.reason()

    @admin.display(description=gettext_lazy("Redis credentials"))
    def credentials(self, obj: Gateway) -> str:
        if obj.redis_password_sha256:
            return _("Redis user %(user)s. New password: manage.py add_gateway %(gateway)s --env-file FILE") % {
                "user": obj.redis_user, "gateway": obj.name}
        return _("none yet (the default Redis user). Issue them: manage.py add_gateway %(gateway)s --env-file "
                 "FILE") % {"gateway": obj.name}

    @admin.display(description=gettext_lazy("robots"), ordering="robots_total")
    def robot_count(self, obj: Gateway) -> int:
        return obj.robots_total

    @admin.display(description=gettext_lazy("lost / dropped"))
    def lost(self, obj: Gateway) -> str:
        values = {"facts": obj.facts_lost, "batches": obj.logs_lost, "lines": obj.logs_dropped,
                  "rejected": obj.facts_rejected}
        if obj.facts_rejected:
            return _("%(facts)s facts, %(batches)s log batches, %(lines)s log lines, %(rejected)s facts "
                     "rejected") % values
        return _("%(facts)s facts, %(batches)s log batches, %(lines)s log lines") % values
