"""Users and groups in the admin site, limited by role.

Django's stock user admin lets anyone with "change user" edit every field of every account,
their own included: a member of the admin role could tick its own "superuser" box. Here, for
anyone who is not a superuser:

- superuser status, staff status and single permissions are shown read-only, on the add and the
  change form: they are left out of the form, so a crafted POST cannot set them;
- the groups offered are the viewer and operator roles only; any other group a user already
  has (the admin role, a group a superuser made) stays as it is;
- on their own account they may change name, e-mail and password, not groups or flags;
- superusers, staff accounts and admin-role members other than themselves can be neither
  opened, changed, given a new password nor deleted: only superusers manage admins;
- groups and what they grant are not editable at all (the group admin is for superusers).

The rules live here, next to roles.py, because they are about the roles: the fleet app owns
them and connects ``admins_are_staff``. fleet/admin.py imports this module so the admin site's
autodiscovery registers it.
"""
from __future__ import annotations

from typing import Any

from django.contrib import admin, messages
from django.contrib.admin.utils import unquote
from django.contrib.auth.admin import GroupAdmin, UserAdmin  # registers the stock ones replaced below
from django.contrib.auth.forms import UserChangeForm
from django.contrib.auth.models import AbstractUser, Group, User
from django.core.exceptions import PermissionDenied
from django.http import HttpRequest, HttpResponse, HttpResponseRedirect
from django.urls import reverse
from django.utils.translation import gettext_lazy

from lifecycle_site.fleet.roles import ADMIN_ROLE, ASSIGNABLE_BY_ADMINS

# What only a superuser sets, on anyone.
SUPERUSER_ONLY_FIELDS = ("is_superuser", "is_staff", "user_permissions")
# What nobody but a superuser changes on their own account.
OWN_ACCOUNT_FIXED_FIELDS = ("groups", "is_active")
# What an admin is told on opening an account only a superuser manages, by privilege()'s reason.
ONLY_FOR_SUPERUSERS = {
    "a superuser": gettext_lazy("The account “%(user)s” is a superuser: only a superuser may open, change or "
                                "delete it, or set its password. Ask a superuser."),
    "a member of the admin role": gettext_lazy("The account “%(user)s” is a member of the admin role: only a "
                                               "superuser may open, change or delete it, or set its password. Ask a "
                                               "superuser."),
    "a staff account": gettext_lazy("The account “%(user)s” is a staff account: only a superuser may open, change "
                                    "or delete it, or set its password. Ask a superuser."),
}


def privilege(user: AbstractUser) -> str | None:
    """Why only a superuser may manage ``user``, in (English) words; None if an admin may."""
    if user.is_superuser:
        return "a superuser"
    if user.groups.filter(name=ADMIN_ROLE).exists():
        return "a member of the admin role"
    if user.is_staff:
        return "a staff account"
    return None


class RoleLimitedUserChangeForm(UserChangeForm):
    def clean_groups(self) -> list[Group]:
        """The groups chosen, plus those the user has that were not offered (the field offers
        a non-superuser the viewer and operator roles only): what cannot be given cannot be
        taken away either."""
        chosen = list(self.cleaned_data["groups"])
        if self.instance.pk is None:
            return chosen
        offered = self.fields["groups"].queryset
        return chosen + list(self.instance.groups.exclude(pk__in=offered.values("pk")))


class RoleLimitedUserAdmin(UserAdmin):
    form = RoleLimitedUserChangeForm

    # -- who may do what: the enforcement (every admin view goes through these) --

    def may_manage(self, request: HttpRequest, obj: AbstractUser | None) -> bool:
        user = request.user
        return user.is_superuser or obj is None or obj.pk == user.pk or privilege(obj) is None

    def has_view_permission(self, request: HttpRequest, obj: AbstractUser | None = None) -> bool:
        return super().has_view_permission(request, obj) and self.may_manage(request, obj)

    def has_change_permission(self, request: HttpRequest, obj: AbstractUser | None = None) -> bool:
        return super().has_change_permission(request, obj) and self.may_manage(request, obj)

    def has_delete_permission(self, request: HttpRequest, obj: AbstractUser | None = None) -> bool:
        if obj is not None and obj.pk == request.user.pk and not request.user.is_superuser:
            return False
        return super().has_delete_permission(request, obj) and self.may_manage(request, obj)

    def get_readonly_fields(self, request: HttpRequest, obj: AbstractUser | None = None) -> list[str]:
        """Read-only fields are left out of the form Django builds, so their POSTed values are
        never read."""
        fields = list(super().get_readonly_fields(request, obj))
        if not request.user.is_superuser:
            fields += SUPERUSER_ONLY_FIELDS
            if obj is not None and obj.pk == request.user.pk:
                fields += OWN_ACCOUNT_FIXED_FIELDS
        return fields

    def formfield_for_manytomany(self, db_field: Any, request: HttpRequest, **kwargs: Any) -> Any:
        if db_field.name == "groups" and not request.user.is_superuser:
            # Anything else POSTed is refused by the field: "not one of the available choices".
            kwargs["queryset"] = Group.objects.filter(name__in=ASSIGNABLE_BY_ADMINS).order_by("name")
        return super().formfield_for_manytomany(db_field, request, **kwargs)

    def save_model(self, request: HttpRequest, obj: AbstractUser, form: Any, change: bool) -> None:
        """Last check before writing: a non-superuser's save leaves both flags as stored."""
        if not request.user.is_superuser:
            stored = {"is_superuser": False, "is_staff": False}
            if change:
                stored = type(obj).objects.values("is_superuser", "is_staff").get(pk=obj.pk)
            if (obj.is_superuser, obj.is_staff) != (stored["is_superuser"], stored["is_staff"]):
                raise PermissionDenied("Only a superuser may set superuser or staff status.")
        super().save_model(request, obj, form, change)

    # -- a readable answer instead of a bare 403 for an account only a superuser manages --

    def refusal(self, request: HttpRequest, object_id: str) -> HttpResponse | None:
        if request.user.is_superuser:
            return None
        target = self.get_object(request, unquote(object_id))
        if target is None or target.pk == request.user.pk:
            return None
        reason = privilege(target)
        if reason is None:
            return None
        self.message_user(request, ONLY_FOR_SUPERUSERS[reason] % {"user": target.get_username()}, messages.ERROR)
        opts = self.opts
        return HttpResponseRedirect(
            reverse(f"admin:{opts.app_label}_{opts.model_name}_changelist", current_app=self.admin_site.name)
        )

    def change_view(self, request: HttpRequest, object_id: str, form_url: str = "", extra_context=None):
        return self.refusal(request, object_id) or super().change_view(request, object_id, form_url, extra_context)

    def delete_view(self, request: HttpRequest, object_id: str, extra_context=None):
        return self.refusal(request, object_id) or super().delete_view(request, object_id, extra_context)

    def history_view(self, request: HttpRequest, object_id: str, extra_context=None):
        return self.refusal(request, object_id) or super().history_view(request, object_id, extra_context)

    def user_change_password(self, request: HttpRequest, id: str, form_url: str = ""):  # noqa: A002
        return self.refusal(request, id) or super().user_change_password(request, id, form_url)


class SuperuserOnlyGroupAdmin(GroupAdmin):
    """Groups are the roles; what a role grants is set in code (roles.py) or by a superuser,
    never by an account that would thereby widen its own role."""

    def has_module_permission(self, request: HttpRequest) -> bool:
        return request.user.is_active and request.user.is_superuser

    def has_view_permission(self, request: HttpRequest, obj: Group | None = None) -> bool:
        return self.has_module_permission(request)

    def has_add_permission(self, request: HttpRequest) -> bool:
        return self.has_module_permission(request)

    def has_change_permission(self, request: HttpRequest, obj: Group | None = None) -> bool:
        return self.has_module_permission(request)

    def has_delete_permission(self, request: HttpRequest, obj: Group | None = None) -> bool:
        return self.has_module_permission(request)


admin.site.unregister(User)
admin.site.register(User, RoleLimitedUserAdmin)
admin.site.unregister(Group)
admin.site.register(Group, SuperuserOnlyGroupAdmin)
