"""The admin's page for launch profiles (admins only, by their role's permissions): the command,
its arguments and environment as JSON, and secret environment values that are never shown
again once saved."""
from __future__ import annotations

import json

from django import forms
from django.contrib import admin
from django.core.exceptions import ValidationError
from django.utils.translation import gettext as _
from django.utils.translation import gettext_lazy

from lifecycle_site.fleet.process_profiles import ProcessProfile

ENV_NAME_LIMIT, ENTRIES_LIMIT, TEXT_LIMIT = 256, 256, 4096


def _strings(value, message: str) -> None:
    """``message``: what the form says when ``value`` is not a list of strings."""
    if not isinstance(value, list) or len(value) > ENTRIES_LIMIT or not all(
            isinstance(v, str) and "\0" not in v and len(v) <= TEXT_LIMIT for v in value):
        raise ValidationError(message)


def _environment(value, message: str) -> None:
    """``message``: what the form says when ``value`` is not an object of names to strings."""
    if not isinstance(value, dict) or len(value) > ENTRIES_LIMIT or not all(
            isinstance(k, str) and k and "=" not in k and "\0" not in k and len(k) <= ENV_NAME_LIMIT
            and isinstance(v, str) and "\0" not in v and len(v) <= TEXT_LIMIT for k, v in value.items()):
        raise ValidationError(message)


class ProcessProfileForm(forms.ModelForm):
    secrets = forms.CharField(
        label=gettext_lazy("secret environment"), required=False, widget=forms.Textarea(attrs={"rows": 3}),
        help_text=gettext_lazy('A JSON object, e.g. {"API_TOKEN": "..."}: replaces the secret values kept (their '
                               "names are listed below; the values are never shown). Leave empty to keep them; {} "
                               "removes them."))

    class Meta:
        model = ProcessProfile
        fields = ("robot", "name", "enabled", "command", "args", "env", "cwd", "respawn", "respawn_delay_s",
                  "max_failures", "failure_window_s", "stop_signal", "stop_grace_s")

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        kept = sorted((self.instance.secret_env or {}).keys())
        if kept:
            self.fields["secrets"].help_text = "%s %s" % (
                self.fields["secrets"].help_text, _("Kept now: %(names)s.") % {"names": ", ".join(kept)})

    def clean_args(self):
        _strings(self.cleaned_data["args"], _("The arguments must be a JSON list of at most %(count)s strings.") % {
            "count": ENTRIES_LIMIT})
        return self.cleaned_data["args"]

    def clean_env(self):
        _environment(self.cleaned_data["env"], _('The environment must be a JSON object of names to strings, e.g. '
                                                 '{"ROS_DOMAIN_ID": "21"}.'))
        return self.cleaned_data["env"]

    def clean_secrets(self):
        text = self.cleaned_data["secrets"].strip()
        if not text:
            return None
        try:
            value = json.loads(text)
        except ValueError:
            raise ValidationError(_("The secret environment must be JSON.")) from None
        _environment(value, _('The secret environment must be a JSON object of names to strings, e.g. '
                              '{"ROS_DOMAIN_ID": "21"}.'))
        return value

    def save(self, commit: bool = True):
        if self.cleaned_data.get("secrets") is not None:
            self.instance.secret_env = self.cleaned_data["secrets"]
        return super().save(commit)


@admin.register(ProcessProfile)
class ProcessProfileAdmin(admin.ModelAdmin):
    form = ProcessProfileForm
    list_display = ("name", "robot", "enabled", "status", "pid", "restarts", "status_since")
    list_filter = ("robot", "enabled", "status")
    list_select_related = ("robot",)
    search_fields = ("name", "command", "robot__name")
    readonly_fields = ("status", "pid", "status_since", "restarts", "last_exit_code", "last_exit_signal",
                       "last_exit_at", "last_message")
