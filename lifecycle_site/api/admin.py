"""API tokens in the admin: made here (shown once, on the page that answers the form), reviewed
and revoked; and the record of every token made or revoked, anywhere.

Who may make a token for whom follows who may manage whom (fleet/accounts_admin.py): a
superuser for anyone; a member of the admin role for itself and for accounts it may manage
(viewers and operators, e.g. a service account for CI), never for a superuser, a staff account
or another admin (that would let it act as them). Admins may revoke any token.
"""
from __future__ import annotations

from django import forms
from django.contrib import admin
from django.contrib.auth import get_user_model
from django.db.models import Q, QuerySet
from django.http import HttpRequest, HttpResponse
from django.template.response import TemplateResponse
from django.utils.translation import gettext as _
from django.utils.translation import gettext_lazy

from lifecycle_site.api.models import MAX_TOKENS_PER_USER, ApiToken, TokenEvent, TooManyTokens
from lifecycle_site.audit.admin import ReadOnlyAdmin
from lifecycle_site.fleet.roles import ADMIN_ROLE

VIA = "admin"


def token_owners(request: HttpRequest) -> QuerySet:
    """The accounts ``request.user`` may make tokens for."""
    users = get_user_model().objects.filter(is_active=True).order_by("username")
    if request.user.is_superuser:
        return users
    managed = users.filter(is_superuser=False, is_staff=False).exclude(groups__name=ADMIN_ROLE)
    return users.filter(Q(pk=request.user.pk) | Q(pk__in=managed.values("pk")))


class NewTokenForm(forms.ModelForm):
    class Meta:
        model = ApiToken
        fields = ("user", "name")
        help_texts = {"user": gettext_lazy("The token acts as this account, with its roles, no more.")}

    def __init__(self, *args, request: HttpRequest | None = None, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.fields["name"].required = True
        if request is not None:
            self.fields["user"].queryset = token_owners(request)
            self.fields["user"].initial = request.user.pk

    def clean(self) -> dict:
        data = super().clean()
        user = data.get("user")
        if user is not None and ApiToken.objects.filter(user=user).count() >= MAX_TOKENS_PER_USER:
            raise forms.ValidationError(str(TooManyTokens.of(user)))
        return data


@admin.register(ApiToken)
class ApiTokenAdmin(admin.ModelAdmin):
    list_display = ("hint", "user", "name", "created", "last_used")
    list_filter = ("user",)
    search_fields = ("name", "hint", "user__username")
    readonly_fields = ("user", "name", "hint", "created", "last_used")

    def has_add_permission(self, request: HttpRequest) -> bool:
        # Everyone who reaches the admin may make tokens, for the accounts token_owners() allows.
        return request.user.is_active and request.user.is_staff

    def has_change_permission(self, request: HttpRequest, obj=None) -> bool:
        return False  # a token is made and revoked, never edited

    def get_readonly_fields(self, request: HttpRequest, obj=None):
        return self.readonly_fields if obj is not None else ()

    def get_fields(self, request: HttpRequest, obj=None):
        return self.readonly_fields if obj is not None else ("user", "name")

    def get_form(self, request: HttpRequest, obj=None, change=False, **kwargs):
        if obj is not None:
            return super().get_form(request, obj, change, **kwargs)

        class BoundNewTokenForm(NewTokenForm):
            def __init__(self, *args, **inner) -> None:
                super().__init__(*args, request=request, **inner)

        return BoundNewTokenForm

    def save_model(self, request: HttpRequest, obj: ApiToken, form, change: bool) -> None:
        # The token is made here, not by ModelAdmin's save: the form's instance gets its record.
        record, token = ApiToken.issue(form.cleaned_data["user"], form.cleaned_data["name"], by=request.user,
                                       via=VIA)
        obj.pk, obj.hint, obj.created = record.pk, record.hint, record.created
        request._new_token = token  # shown once, in the answer to this POST (response_add)

    def response_add(self, request: HttpRequest, obj: ApiToken, post_url_continue=None) -> HttpResponse:
        context = {**self.admin_site.each_context(request), "opts": self.opts, "token": request._new_token,
                   "record": obj, "title": _("New API token")}
        return TemplateResponse(request, "admin/api/apitoken/created.html", context)

    def log_addition(self, request, obj, message):
        return None  # on record as a TokenEvent instead (with the token's hint, not its value)

    def delete_model(self, request: HttpRequest, obj: ApiToken) -> None:
        obj.revoke(by=request.user, via=VIA)

    def delete_queryset(self, request: HttpRequest, queryset: QuerySet) -> None:
        for token in queryset.select_related("user"):
            token.revoke(by=request.user, via=VIA)


@admin.register(TokenEvent)
class TokenEventAdmin(ReadOnlyAdmin):
    """Tokens made and revoked: read-only, for whoever may review tokens."""

    list_display = ("at", "action", "hint", "token_name", "owner_name", "actor_name", "via")
    list_filter = ("action", "via")
    search_fields = ("hint", "token_name", "owner_name", "actor_name")
    date_hierarchy = "at"

    def _reviewer(self, request: HttpRequest) -> bool:
        return request.user.is_active and request.user.is_staff and request.user.has_perm("api.view_apitoken")

    def has_module_permission(self, request: HttpRequest) -> bool:
        return self._reviewer(request)

    def has_view_permission(self, request: HttpRequest, obj=None) -> bool:
        return self._reviewer(request)
