"""The three roles of the product as Django groups: viewer, operator, admin.

Kept in code (re-applied after every migrate) so that a fresh database, a test database
after a flush and an upgraded installation all have the same roles.
"""
from __future__ import annotations

from typing import Any

VIEW = [
    "fleet.view_robot",
    "fleet.view_managednode",
    "fleet.view_logrecord",
    "fleet.view_nodeabsence",
    "audit.view_transitionrecord",
    "audit.view_parameterrecord",
    "audit.view_processrecord",
    "fleet.view_processprofile",
    "alerts.view_alert",
    "modes.view_mode",
    "modes.view_currentmode",
]
OPERATE = VIEW + ["fleet.operate_node", "alerts.acknowledge_alert"]
ADMINISTER = OPERATE + [
    "fleet.add_robot",
    "fleet.change_robot",
    "fleet.delete_robot",
    "fleet.add_managednode",
    "fleet.change_managednode",
    "fleet.delete_managednode",
    "fleet.add_processprofile",
    "fleet.change_processprofile",
    "fleet.delete_processprofile",
    "modes.add_mode",
    "modes.change_mode",
    "modes.delete_mode",
    "auth.view_user",
    "auth.add_user",
    "auth.change_user",
    "api.view_apitoken",
    "api.delete_apitoken",
    "audit.view_accessdenial",
    "alerts.view_rule",
    "alerts.add_rule",
    "alerts.change_rule",
    "alerts.delete_rule",
    "alerts.view_receiver",
    "alerts.add_receiver",
    "alerts.change_receiver",
    "alerts.delete_receiver",
    "alerts.view_delivery",
    "sign_in.view_directoryaccount",
]
ROLES: dict[str, list[str]] = {"viewer": VIEW, "operator": OPERATE, "admin": ADMINISTER}
ADMIN_ROLE = "admin"
#: The permission that tells a role from the one below it (operations.py names a role per operation).
ROLE_PERMISSION = {"viewer": "fleet.view_robot", "operator": "fleet.operate_node", "admin": "fleet.change_robot"}
#: The roles a member of the admin role may give or take away; the admin role itself, the
#: staff and superuser flags and single permissions are a superuser's (see accounts_admin).
ASSIGNABLE_BY_ADMINS = ("viewer", "operator")


def ensure_roles(**_: Any) -> None:
    from django.contrib.auth.models import Group, Permission

    for role, codenames in ROLES.items():
        group, _created = Group.objects.get_or_create(name=role)
        wanted = []
        for dotted in codenames:
            app_label, codename = dotted.split(".")
            permission = Permission.objects.filter(
                content_type__app_label=app_label, codename=codename
            ).first()
            if permission is not None:
                wanted.append(permission)
        group.permissions.set(wanted)


def admins_are_staff(sender, instance, action: str, **_: Any) -> None:
    """Members of the admin role get Django's staff flag, which opens the admin site to them.

    It follows the admin group only, which only a superuser hands out, and the admin role
    cannot change the groups of a staff account (accounts_admin): so it neither makes nor
    unmakes staff on a non-superuser's behalf. It never touches a superuser."""
    if action not in ("post_add", "post_remove", "post_clear"):
        return
    from django.contrib.auth import get_user_model

    if not isinstance(instance, get_user_model()):
        return
    is_admin = instance.groups.filter(name=ADMIN_ROLE).exists()
    if instance.is_staff != is_admin and not instance.is_superuser:
        instance.is_staff = is_admin
        instance.save(update_fields=["is_staff"])


def may_act_as(user: Any, role: str) -> bool:
    """Whether ``user`` holds ``role``'s rights (an unknown role: nobody does)."""
    permission = ROLE_PERMISSION.get(role)
    return permission is not None and user.has_perm(permission)
