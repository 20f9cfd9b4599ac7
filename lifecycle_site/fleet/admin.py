from django import forms
from django.contrib import admin
from django.urls import reverse
from django.utils.html import format_html
from django.utils.translation import gettext as _
from django.utils.translation import gettext_lazy

from lifecycle_site.fleet import (
    accounts_admin,  # noqa: F401  (users and groups, limited by role)
    process_admin,  # noqa: F401  (launch profiles)
)
from lifecycle_site.fleet.models import ManagedNode, NodeAbsence, Robot


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
    verbose_name = gettext_lazy("managed node")  # (the model's own names, in English as before)
    verbose_name_plural = gettext_lazy("managed nodes")

    @admin.display(description=gettext_lazy("dashboard"))
    def dashboard(self, obj: ManagedNode) -> str:
        return format_html('<a href="{}">{}</a>', dashboard_url(obj), _("node page")) if obj.pk and obj.key else ""


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
    verbose_name_plural = gettext_lazy("absences (newest first; the timeline page draws them)")

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

    @admin.display(description=gettext_lazy("dashboard"))
    def dashboard(self, obj: ManagedNode) -> str:
        return format_html('<a href="{}">{}</a>', dashboard_url(obj), _("node page"))
