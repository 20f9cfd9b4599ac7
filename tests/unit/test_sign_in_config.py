"""Company sign-in settings from the environment: the role mapping, what is required, TLS always."""
from __future__ import annotations

import ssl

import pytest

from lifecycle_site.sign_in import config
from lifecycle_site.sign_in.accounts import role_for
from ros_gateway.shared.environment import SettingError

OIDC = {
    "LIFECYCLE_OIDC_CLIENT_ID": "lifecycle", "LIFECYCLE_OIDC_CLIENT_SECRET": "s3cret",
    "LIFECYCLE_OIDC_AUTHORIZATION_URL": "https://idp.plant/auth", "LIFECYCLE_OIDC_TOKEN_URL": "https://idp.plant/token",
    "LIFECYCLE_OIDC_USERINFO_URL": "https://idp.plant/userinfo", "LIFECYCLE_OIDC_JWKS_URL": "https://idp.plant/jwks",
    "LIFECYCLE_OIDC_ROLES": "operator=Shift-Leads,operators;admin=plant-it",
}


def test_role_mapping_is_case_blind_and_refuses_what_it_cannot_read():
    mapping = config.role_mapping("R", {"R": " admin = Plant-IT ; operator=ops, shift ;viewer=staff;"})
    assert mapping == {"plant-it": "admin", "ops": "operator", "shift": "operator", "staff": "viewer"}
    with pytest.raises(SettingError, match="roles viewer, operator and admin"):
        config.role_mapping("R", {"R": "superuser=plant-it"})
    with pytest.raises(SettingError, match="roles viewer, operator and admin"):
        config.role_mapping("R", {"R": "plant-it"})
    with pytest.raises(SettingError, match="mapped to two roles"):
        config.role_mapping("R", {"R": "admin=ops;operator=OPS"})


def test_the_highest_mapped_role_wins_and_no_mapped_group_means_none():
    mapping = {"staff": "viewer", "ops": "operator", "plant-it": "admin"}
    assert role_for(["Staff", "OPS"], mapping) == "operator"
    assert role_for(["staff", "plant-it", "ops"], mapping) == "admin"
    assert role_for(["visitors"], mapping) is None
    assert role_for([], mapping) is None


def test_oidc_is_off_without_a_client_and_complete_with_one():
    assert config.oidc_settings({}) == {}
    settings = config.oidc_settings(OIDC)
    assert settings["OIDC_USE_PKCE"] is True and settings["OIDC_PKCE_CODE_CHALLENGE_METHOD"] == "S256"
    assert settings["OIDC_RP_SIGN_ALGO"] == "RS256" and settings["OIDC_VERIFY_SSL"] is True
    assert settings["LIFECYCLE_OIDC_ROLES"] == {"shift-leads": "operator", "operators": "operator", "plant-it": "admin"}
    with pytest.raises(SettingError, match="LIFECYCLE_OIDC_TOKEN_URL"):
        config.oidc_settings({k: v for k, v in OIDC.items() if k != "LIFECYCLE_OIDC_TOKEN_URL"})


def test_ldap_always_checks_the_directory_certificate(tmp_path):
    base = {"LIFECYCLE_LDAP_USER_BASE": "ou=people,dc=plant", "LIFECYCLE_LDAP_ROLES": "operator=ops"}
    assert config.ldap_settings({}) == {}
    plain = config.ldap_settings({**base, "LIFECYCLE_LDAP_URL": "ldap://dir.plant"})
    assert plain["LDAP_AUTH_USE_TLS"] is True and plain["LDAP_AUTH_CONNECT_USE_SSL"] is False  # StartTLS
    assert plain["LDAP_AUTH_TLS_ARGS"]["validate"] == ssl.CERT_REQUIRED
    assert plain["LDAP_AUTH_POOL_ACTIVE"] == 1  # one pass over the servers, not for ever
    tls = config.ldap_settings({**base, "LIFECYCLE_LDAP_URL": "ldaps://dir.plant"})
    assert tls["LDAP_AUTH_CONNECT_USE_SSL"] is True
    assert tls["LDAP_AUTH_CONNECT_ARGS"]["tls"].validate == ssl.CERT_REQUIRED
    ad = config.ldap_settings({**base, "LIFECYCLE_LDAP_URL": "ldaps://dc1.plant",
                               "LIFECYCLE_LDAP_AD_DOMAIN": "plant.local"})
    assert ad["LDAP_AUTH_USER_FIELDS"]["username"] == "sAMAccountName" and ad["LDAP_AUTH_OBJECT_CLASS"] == "user"
    with pytest.raises(SettingError, match="all of one kind"):
        config.ldap_settings({**base, "LIFECYCLE_LDAP_URL": "ldaps://a,ldap://b"})
    with pytest.raises(SettingError, match="expected ldaps://"):
        config.ldap_settings({**base, "LIFECYCLE_LDAP_URL": "http://dir.plant"})
    with pytest.raises(SettingError, match="no such file"):
        config.ldap_settings({**base, "LIFECYCLE_LDAP_URL": "ldaps://a", "LIFECYCLE_LDAP_CA_FILE": str(tmp_path / "x")})
    with pytest.raises(SettingError, match="LIFECYCLE_LDAP_ROLES"):
        config.ldap_settings({"LIFECYCLE_LDAP_URL": "ldaps://a", "LIFECYCLE_LDAP_USER_BASE": "ou=people"})


def test_a_directory_session_lasts_a_shift_unless_told_otherwise():
    assert config.directory_session_hours({}) == 12
    assert config.directory_session_hours({"LIFECYCLE_DIRECTORY_SESSION_HOURS": "0.5"}) == 0.5
    for bad in ("0", "-1", "337", "eight", "nan"):
        with pytest.raises(SettingError, match="LIFECYCLE_DIRECTORY_SESSION_HOURS"):
            config.directory_session_hours({"LIFECYCLE_DIRECTORY_SESSION_HOURS": bad})


def test_a_directory_accounts_tokens_last_a_month_after_its_sign_in_unless_told_otherwise():
    assert config.directory_token_days({}) == 30
    assert config.directory_token_days({"LIFECYCLE_DIRECTORY_TOKEN_DAYS": "7"}) == 7
    for bad in ("0", "-1", "3651", "a month", "nan"):
        with pytest.raises(SettingError, match="LIFECYCLE_DIRECTORY_TOKEN_DAYS"):
            config.directory_token_days({"LIFECYCLE_DIRECTORY_TOKEN_DAYS": bad})


def test_the_issuer_alone_stands_for_the_endpoints_and_must_be_an_http_url():
    only_issuer = {k: v for k, v in OIDC.items() if not k.endswith("_URL")}
    settings = config.oidc_settings({**only_issuer, "LIFECYCLE_OIDC_ISSUER": " https://idp.plant/realms/x/ "})
    assert settings["OIDC_OP_ISSUER"] == "https://idp.plant/realms/x"
    assert settings["OIDC_OP_TOKEN_ENDPOINT"] == settings["OIDC_OP_AUTHORIZATION_ENDPOINT"] == ""  # discovered
    with_one = config.oidc_settings({**only_issuer, "LIFECYCLE_OIDC_ISSUER": "https://idp.plant",
                                     "LIFECYCLE_OIDC_TOKEN_URL": "https://idp.plant/t"})
    assert with_one["OIDC_OP_TOKEN_ENDPOINT"] == "https://idp.plant/t"  # set: it wins over the document's
    with pytest.raises(SettingError, match="without LIFECYCLE_OIDC_ISSUER.*needs LIFECYCLE_OIDC_AUTHORIZATION_URL"):
        config.oidc_settings(only_issuer)
    for wrong in ("idp.plant", "ftp://idp.plant", "https://idp.plant/?realm=x", "https:///x"):
        with pytest.raises(SettingError, match="LIFECYCLE_OIDC_ISSUER=.*an https URL"):
            config.oidc_settings({**only_issuer, "LIFECYCLE_OIDC_ISSUER": wrong})


def test_origin_of_an_end_session_address():
    assert config.origin("https://idp.plant:8443/realms/x/logout?y=1") == "https://idp.plant:8443"


def test_the_compose_file_and_env_example_carry_every_sign_in_variable():
    """An operator's docker/.env reaches the site: the web service passes each variable the sign-in
    settings read, and docker/env.example lists it."""
    import re
    from pathlib import Path

    import yaml

    root = Path(__file__).resolve().parents[2]
    read = set(re.findall(r"LIFECYCLE_(?:OIDC|LDAP|DIRECTORY)_[A-Z_]+", Path(config.__file__).read_text()))
    web = yaml.safe_load((root / "docker" / "docker-compose.yml").read_text())["services"]["web"]["environment"]
    example = set(re.findall(r"^(LIFECYCLE_[A-Z_]+)=", (root / "docker" / "env.example").read_text(), re.M))
    assert len(read) > 20
    assert read - set(web) == set(), "not passed to the web service"
    assert read - example == set(), "not in docker/env.example"


def test_log_out_may_go_to_the_issuers_origin_when_its_logout_is_discovered():
    """The page's Content-Security-Policy lets Log out's form go to the provider's origin: the
    logout URL's when set, else the issuer's (sign_in.discovery uses a discovered end-session
    endpoint only on that origin)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    only_issuer = {k: v for k, v in OIDC.items() if not k.endswith("_URL")}
    environ = {**os.environ, **only_issuer, "LIFECYCLE_OIDC_ISSUER": "https://idp.plant:8443/realms/x",
               "DJANGO_SETTINGS_MODULE": "lifecycle_site.settings"}
    done = subprocess.run([sys.executable, "-c", "from django.conf import settings; "
                           "print(settings.CONTENT_SECURITY_POLICY['DIRECTIVES']['form-action'])"],
                          cwd=Path(__file__).resolve().parents[2], env=environ, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[\"'self'\", 'https://idp.plant:8443']"
