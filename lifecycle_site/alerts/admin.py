"""Alert rules and receivers (the admin role manages them), alerts and the delivery log (read-only)."""
from __future__ import annotations

from django import forms
from django.contrib import admin
from django.utils.translation import gettext as _
from django.utils.translation import gettext_lazy

from lifecycle_site.alerts import destinations
from lifecycle_site.alerts.models import Alert, Delivery, Receiver, Rule
from lifecycle_site.audit.admin import ReadOnlyAdmin


class ReceiverForm(forms.ModelForm):
    """The secret is entered, never shown: left empty, the stored one is kept."""

    secret = forms.CharField(
        required=False, strip=True, widget=forms.PasswordInput(render_value=False),
        help_text=gettext_lazy("Key of the HMAC-SHA256 signature (X-Lifecycle-Signature). Left empty, the stored "
                               "key is kept; it is never shown again."),
    )
    clear_secret = forms.BooleanField(required=False, help_text=gettext_lazy("Remove the stored key: send unsigned."))

    class Meta:
        model = Receiver
        fields = ["name", "kind", "url", "secret", "clear_secret", "emails", "enabled"]
        help_texts = {"url": gettext_lazy("http:// or https:// address that takes a JSON POST (redirects are not "
                                          "followed). Internal addresses only as LIFECYCLE_WEBHOOK_ALLOW lists them; "
                                          "no user name or password in it (the secret signs each request).")}

    def save(self, commit: bool = True) -> Receiver:
        receiver = super().save(commit=False)
        if self.cleaned_data.get("clear_secret"):
            receiver.secret = ""
        elif not self.cleaned_data.get("secret") and receiver.pk:
            receiver.secret = Receiver.objects.filter(pk=receiver.pk).values_list("secret", flat=True).first() or ""
        if commit:
            receiver.save()
        return receiver


@admin.register(Receiver)
class ReceiverAdmin(admin.ModelAdmin):
    form = ReceiverForm
    list_display = ("name", "kind", "target", "signed", "enabled", "delivered", "failed", "dropped")
    readonly_fields = ("delivered", "failed", "dropped")

    @admin.display(description=gettext_lazy("sends to"))
    def target(self, receiver: Receiver) -> str:
        return destinations.redact(receiver.url) if receiver.kind == Receiver.Kind.WEBHOOK else receiver.emails

    @admin.display(boolean=True, description=gettext_lazy("signed"))
    def signed(self, receiver: Receiver) -> bool:
        return bool(receiver.secret)


@admin.register(Rule)
class RuleAdmin(admin.ModelAdmin):
    list_display = ("name", "kind", "state", "for_seconds", "keep_firing_seconds", "scope", "enabled")
    list_filter = ("kind", "enabled")
    filter_horizontal = ("receivers",)
    fields = ("name", "enabled", "kind", "state", "for_seconds", "keep_firing_seconds", "gateway", "robot",
              "node_pattern", "status_pattern", "level", "receivers")

    @admin.display(description=gettext_lazy("scope"))
    def scope(self, rule: Rule) -> str:
        parts = [_("gateway %(gateway)s") % {"gateway": rule.gateway} if rule.gateway_id else "",
                 _("robot %(robot)s") % {"robot": rule.robot} if rule.robot_id else "",
                 rule.node_pattern, rule.status_pattern]
        return ", ".join(p for p in parts if p) or _("fleet")


@admin.register(Alert)
class AlertAdmin(ReadOnlyAdmin):
    list_display = ("id", "rule_name", "subject", "status", "fired_at", "acknowledged_by_name", "resolved_at")
    list_filter = ("status", "rule_name")
    search_fields = ("subject", "summary")


@admin.register(Delivery)
class DeliveryAdmin(ReadOnlyAdmin):
    list_display = ("at", "receiver_name", "event", "alert", "attempt", "outcome", "status_code", "duration_ms",
                    "error")
    list_filter = ("outcome", "event", "receiver_name")
