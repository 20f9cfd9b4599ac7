"""Who may change whom in the admin site (/admin/): the admin role manages viewers and
operators; only a superuser grants superuser, staff, permissions or the admin role, and only a
superuser changes a superuser, a staff account or another admin. Every request here goes
through the real admin views and the real SQLite database, as crafted POSTs would."""
from __future__ import annotations

import pytest
from django.contrib.auth import get_user_model
from django.contrib.auth.models import Group, Permission
from django.test import Client

from tests.conftest import make_user

PASSWORD = "a-test-password-123"


def change_url(user) -> str:
    return f"/admin/auth/user/{user.pk}/change/"


def change_form(user, **overrides) -> dict:
    """Everything the stock user change form posts, as a browser would, plus ``overrides``."""
    data = {
        "username": user.username,
        "first_name": user.first_name,
        "last_name": user.last_name,
        "email": user.email,
        "is_active": "on",
        "date_joined_0": user.date_joined.strftime("%Y-%m-%d"),
        "date_joined_1": user.date_joined.strftime("%H:%M:%S"),
        "initial-date_joined_0": user.date_joined.strftime("%Y-%m-%d"),
        "initial-date_joined_1": user.date_joined.strftime("%H:%M:%S"),
        "groups": [group.pk for group in user.groups.all()],
    }
    data.update(overrides)
    return {key: value for key, value in data.items() if value is not None}


def role(name: str) -> Group:
    return Group.objects.get(name=name)


def group_names(user) -> set[str]:
    return set(user.groups.values_list("name", flat=True))


def refused(response) -> bool:
    """The admin site said no: 403, or a redirect away from the page (with a message)."""
    return response.status_code == 403 or (
        response.status_code == 302 and response["Location"].rstrip("/").endswith("/admin/auth/user")
    )


@pytest.fixture
def ada(db):
    """A member of the admin role: staff (through the role), not a superuser."""
    user = make_user("ada-admin", "admin")
    user.refresh_from_db()
    assert user.is_staff and not user.is_superuser
    return user


@pytest.fixture
def ada_client(ada) -> Client:
    client = Client()
    client.force_login(ada)
    return client


@pytest.fixture
def root(db):
    return get_user_model().objects.create_superuser("sam-super", "sam@plant.example", PASSWORD)


@pytest.fixture
def root_client(root) -> Client:
    client = Client()
    client.force_login(root)
    return client


def test_admin_role_cannot_make_itself_superuser(ada, ada_client):
    change_group = Permission.objects.get(content_type__app_label="auth", codename="change_group")
    response = ada_client.post(
        change_url(ada),
        change_form(
            ada,
            first_name="Ada",
            email="ada@plant.example",
            is_superuser="on",
            is_staff="on",
            user_permissions=[change_group.pk],
            groups=[role("viewer").pk],
        ),
    )
    assert response.status_code in (200, 302)
    ada.refresh_from_db()
    assert not ada.is_superuser
    assert ada.is_staff  # still from the role, not from the form
    assert not ada.user_permissions.exists()
    assert group_names(ada) == {"admin"}  # its own groups are not its to change
    # What it may change on its own account did change.
    assert (ada.first_name, ada.email) == ("Ada", "ada@plant.example")
    # Its own page and the list of users still open.
    assert ada_client.get(change_url(ada)).status_code == 200
    assert ada_client.get("/admin/auth/user/").status_code == 200


def test_admin_role_cannot_open_or_change_a_superuser(ada_client, root):
    assert refused(ada_client.get(change_url(root)))
    told = ada_client.get(change_url(root), follow=True).content.decode()
    assert "is a superuser: only a superuser may open, change or delete it" in told
    response = ada_client.post(change_url(root), change_form(root, email="taken@evil.example"))
    assert refused(response)
    takeover = ada_client.post(
        f"/admin/auth/user/{root.pk}/password/",
        {"password1": "another-password-456", "password2": "another-password-456", "usable_password": "true"},
    )
    assert refused(takeover)
    assert refused(ada_client.get(f"/admin/auth/user/{root.pk}/delete/"))
    root.refresh_from_db()
    assert root.email == "sam@plant.example" and root.check_password(PASSWORD)
    assert root.is_superuser


def test_admin_role_cannot_change_another_admin(ada_client):
    alan = make_user("alan-admin", "admin")
    alan.refresh_from_db()
    assert refused(ada_client.get(change_url(alan)))
    response = ada_client.post(change_url(alan), change_form(alan, groups=[role("viewer").pk], is_active=None))
    assert refused(response)
    alan.refresh_from_db()
    assert group_names(alan) == {"admin"} and alan.is_staff and alan.is_active


def test_admin_role_cannot_put_anyone_in_the_admin_role(ada_client, root_client):
    olga = make_user("olga-operator", "operator")
    response = ada_client.post(change_url(olga), change_form(olga, groups=[role("admin").pk]))
    assert response.status_code == 200  # the form is shown again with the refusal
    assert "not one of the available choices" in response.content.decode()
    olga.refresh_from_db()
    assert group_names(olga) == {"operator"} and not olga.is_staff

    # A superuser may: the same request from it makes Olga an admin (and staff).
    response = root_client.post(change_url(olga), change_form(olga, groups=[role("admin").pk]))
    assert response.status_code == 302
    olga.refresh_from_db()
    assert group_names(olga) == {"admin"} and olga.is_staff


def test_admin_role_creates_viewers_and_operators_only(ada_client):
    response = ada_client.post(
        "/admin/auth/user/add/",
        {
            "username": "nina-new",
            "usable_password": "true",
            "password1": "a-fresh-password-789",
            "password2": "a-fresh-password-789",
            "is_superuser": "on",
            "is_staff": "on",
        },
    )
    assert response.status_code == 302
    nina = get_user_model().objects.get(username="nina-new")
    assert not nina.is_superuser and not nina.is_staff

    page = ada_client.get(change_url(nina))
    assert page.status_code == 200
    offered = {str(choice[1]) for choice in page.context["adminform"].form.fields["groups"].choices}
    assert offered == {"viewer", "operator"}

    response = ada_client.post(
        change_url(nina),
        change_form(nina, groups=[role("operator").pk], is_superuser="on", is_staff="on"),
    )
    assert response.status_code == 302
    nina.refresh_from_db()
    assert group_names(nina) == {"operator"}
    assert not nina.is_superuser and not nina.is_staff
    assert nina.check_password("a-fresh-password-789")


def test_admin_role_keeps_groups_it_may_not_assign(ada_client):
    """Changing a viewer's role leaves a group that only a superuser manages in place."""
    night_shift = Group.objects.create(name="night-shift")
    vera = make_user("vera-viewer", "viewer")
    vera.groups.add(night_shift)
    response = ada_client.post(change_url(vera), change_form(vera, groups=[role("operator").pk]))
    assert response.status_code == 302
    vera.refresh_from_db()
    assert group_names(vera) == {"operator", "night-shift"}


def test_only_a_superuser_grants_superuser_staff_and_permissions(ada_client, root_client, ada):
    view_robot = Permission.objects.get(content_type__app_label="fleet", codename="view_robot")
    olga = make_user("olga-operator", "operator")
    grant = change_form(olga, is_superuser="on", is_staff="on", user_permissions=[view_robot.pk])
    response = ada_client.post(change_url(olga), grant)
    assert response.status_code == 302  # saved, without what the admin role may not grant
    olga.refresh_from_db()
    assert not olga.is_superuser and not olga.is_staff and not olga.user_permissions.exists()

    response = root_client.post(change_url(olga), grant)
    assert response.status_code == 302
    olga.refresh_from_db()
    assert olga.is_superuser and olga.is_staff and list(olga.user_permissions.all()) == [view_robot]

    # And it changes an admin, which the admin role itself may not.
    response = root_client.post(change_url(ada), change_form(ada, groups=[role("operator").pk], is_staff=None))
    assert response.status_code == 302
    ada.refresh_from_db()
    assert group_names(ada) == {"operator"} and not ada.is_staff


def test_groups_and_their_permissions_are_for_superusers_only(root_client):
    """Even a staff account someone gave the group permissions cannot widen a role."""
    staff = make_user("gus-groups", None)
    staff.is_staff = True
    staff.save()
    staff.user_permissions.set(
        Permission.objects.filter(content_type__app_label="auth", codename__in=["view_group", "change_group"])
    )
    client = Client()
    client.force_login(staff)
    viewer = role("viewer")
    before = set(viewer.permissions.values_list("pk", flat=True))
    superuser_perm = Permission.objects.get(content_type__app_label="auth", codename="change_user")
    group_url = f"/admin/auth/group/{viewer.pk}/change/"
    assert client.get(group_url).status_code == 403
    response = client.post(group_url, {"name": "viewer", "permissions": [*before, superuser_perm.pk]})
    assert response.status_code == 403
    assert set(viewer.permissions.values_list("pk", flat=True)) == before

    assert root_client.get(group_url).status_code == 200


def test_the_roles_are_complete_after_the_first_migrate(db):
    """The test database is made by one migrate, as a fresh install is: every permission a role
    names exists then and is in the role (the audit and api apps migrate after fleet)."""
    from lifecycle_site.fleet.roles import ROLES

    for role, dotted in ROLES.items():
        have = {f"{p.content_type.app_label}.{p.codename}"
                for p in Group.objects.get(name=role).permissions.select_related("content_type")}
        assert have == set(dotted), f"{role} lacks {set(dotted) - have}"


def test_a_password_shorter_than_twelve_characters_is_refused(ada_client):
    """OWASP ASVS 2.1.1: at least 12 characters (Django's default minimum is 8)."""
    response = ada_client.post(
        "/admin/auth/user/add/",
        {"username": "short-pw", "usable_password": "true", "password1": "Xq7-pl4n-9k", "password2": "Xq7-pl4n-9k"},
    )
    assert response.status_code == 200  # the form again, with the reason
    assert "at least 12 characters" in response.content.decode()
    assert not get_user_model().objects.filter(username="short-pw").exists()
