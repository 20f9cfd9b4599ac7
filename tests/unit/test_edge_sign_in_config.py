"""On an Industrial Edge device the app configuration (cfg-data/param.json) sets company sign-in
and the language: docker/runtime/sign_in_env.py turns part "signIn" (config_env.py site.language) into the
variables of docs/sign-in.md and docs/translation.md, checks what it can without Django, and
writes the CA certificates given as PEM to files the variables name."""
from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from lifecycle_site.sign_in import config as site_sign_in

RUNTIME = Path(__file__).resolve().parents[2] / "docker" / "runtime"
# docker/runtime is no package: its scripts import each other from their own folder (sys.path[0]),
# and so do these tests; a module of that name from elsewhere must not stand in for them.
sys.path.insert(0, str(RUNTIME))
for _name in ("config_env", "sign_in_env"):
    sys.modules.pop(_name, None)
import config_env  # noqa: E402
import sign_in_env  # noqa: E402

sys.path.remove(str(RUNTIME))
ConfigError = config_env.ConfigError


def all_env(config: dict, write_files: bool = False) -> dict[str, str]:
    """What a web container exports: settings_env's variables and sign_in_env's."""
    return {**config_env.settings_env(config), **sign_in_env.sign_in_env(config, write_files)}

PEM = "-----BEGIN CERTIFICATE-----\nMIIBszCCAVmgAwIBAgIUXtestonly\n-----END CERTIFICATE-----"
IDP = "https://idp.plant.local/realms/plant/protocol/openid-connect"


def full_config() -> dict:
    return {
        "site": {"language": "DE"},
        "signIn": {
            "sessionHours": 8,
            "tokenDays": 14,
            "oidc": {
                "clientId": "lifecycle", "clientSecret": "s3cret-Value",
                "authorizationUrl": f"{IDP}/auth", "tokenUrl": f"{IDP}/token", "userinfoUrl": f"{IDP}/userinfo",
                "jwksUrl": f"{IDP}/certs", "logoutUrl": f"{IDP}/logout",
                "roles": "operator=lifecycle-operators;admin=plant-it",
                "groupsClaim": "roles", "buttonName": "Plant account", "caCertificate": PEM,
            },
            "ldap": {
                "url": "ldaps://dir1.plant.local:636, ldaps://dir2.plant.local:636",
                "caCertificate": PEM + "\n",
                "userBase": "ou=people,dc=plant,dc=local", "groupBase": "ou=groups,dc=plant,dc=local",
                "roles": {"viewer": ["staff"], "operator": ["shift-leads", "operators"], "admin": ["plant-it"]},
                "adDomain": "plant.local", "bindUser": "cn=lookup,dc=plant,dc=local", "bindPassword": "b1nd pw",
            },
        },
    }


@pytest.fixture(autouse=True)
def ca_files(monkeypatch, tmp_path):
    """The CA files in this test's folder; no sign-in variable of this process's environment
    (sign_in_env fills a gap from there)."""
    for name in list(os.environ):
        if name.startswith(("LIFECYCLE_OIDC_", "LIFECYCLE_LDAP_")):
            monkeypatch.delenv(name)
    monkeypatch.setattr(sign_in_env, "OIDC_CA_FILE", tmp_path / "oidc-ca.crt")
    monkeypatch.setattr(sign_in_env, "LDAP_CA_FILE", tmp_path / "ldap-ca.crt")
    return tmp_path / "oidc-ca.crt", tmp_path / "ldap-ca.crt"


def read(monkeypatch, tmp_path, config) -> dict:
    """read_config of this configuration written as the app configuration file."""
    path = tmp_path / "param.json"
    path.write_text(json.dumps(config))
    monkeypatch.setattr(config_env, "CONFIG_FILE", path)
    return config_env.read_config()


def test_a_full_sign_in_part_becomes_the_variables_of_docs_sign_in(monkeypatch, tmp_path, ca_files):
    oidc_ca, ldap_ca = ca_files
    env = all_env(read(monkeypatch, tmp_path, full_config()))
    assert env == {
        "LIFECYCLE_LANGUAGE": "de",
        "LIFECYCLE_DIRECTORY_SESSION_HOURS": "8",
        "LIFECYCLE_DIRECTORY_TOKEN_DAYS": "14",
        "LIFECYCLE_OIDC_CLIENT_ID": "lifecycle",
        "LIFECYCLE_OIDC_CLIENT_SECRET": "s3cret-Value",
        "LIFECYCLE_OIDC_AUTHORIZATION_URL": f"{IDP}/auth",
        "LIFECYCLE_OIDC_TOKEN_URL": f"{IDP}/token",
        "LIFECYCLE_OIDC_USERINFO_URL": f"{IDP}/userinfo",
        "LIFECYCLE_OIDC_JWKS_URL": f"{IDP}/certs",
        "LIFECYCLE_OIDC_LOGOUT_URL": f"{IDP}/logout",
        "LIFECYCLE_OIDC_ROLES": "operator=lifecycle-operators;admin=plant-it",
        "LIFECYCLE_OIDC_GROUPS_CLAIM": "roles",
        "LIFECYCLE_OIDC_NAME": "Plant account",
        "LIFECYCLE_OIDC_CA_FILE": str(oidc_ca),
        "LIFECYCLE_LDAP_URL": "ldaps://dir1.plant.local:636,ldaps://dir2.plant.local:636",
        "LIFECYCLE_LDAP_CA_FILE": str(ldap_ca),
        "LIFECYCLE_LDAP_USER_BASE": "ou=people,dc=plant,dc=local",
        "LIFECYCLE_LDAP_GROUP_BASE": "ou=groups,dc=plant,dc=local",
        "LIFECYCLE_LDAP_ROLES": "viewer=staff;operator=shift-leads,operators;admin=plant-it",
        "LIFECYCLE_LDAP_AD_DOMAIN": "plant.local",
        "LIFECYCLE_LDAP_BIND_USER": "cn=lookup,dc=plant,dc=local",
        "LIFECYCLE_LDAP_BIND_PASSWORD": "b1nd pw",
    }
    # Written out, the site's own reading of the variables accepts them as they are.
    env = all_env(full_config(), write_files=True)
    oidc = site_sign_in.oidc_settings(env)
    assert oidc["OIDC_VERIFY_SSL"] == str(oidc_ca) and oidc["LIFECYCLE_OIDC_ROLES"] == {
        "lifecycle-operators": "operator", "plant-it": "admin"}
    assert site_sign_in.directory_session_hours(env) == 8 and site_sign_in.directory_token_days(env) == 14
    ldap = site_sign_in.ldap_settings(env)
    assert ldap["LDAP_AUTH_URL"] == ["ldaps://dir1.plant.local:636", "ldaps://dir2.plant.local:636"]
    assert ldap["LDAP_AUTH_TLS_ARGS"]["ca_certs_file"] == str(ldap_ca)


def test_an_empty_sign_in_part_sets_nothing(monkeypatch, tmp_path):
    """What the IEM form writes when nobody fills it in (the demo's param.json)."""
    demo = json.loads((RUNTIME.parent / "edge" / "cfg-data" / "param.json").read_text())
    env = all_env(read(monkeypatch, tmp_path, demo), write_files=True)
    assert not [name for name in env if name.startswith(("LIFECYCLE_OIDC_", "LIFECYCLE_LDAP_"))]
    assert not list(tmp_path.glob("*.crt"))


@pytest.mark.parametrize("roles, text", [
    ({"viewer": ["g1"], "operator": ["g2", "g3"], "admin": []}, "viewer=g1;operator=g2,g3"),
    ({"Admin": "plant-it, it-ops", "viewer": "", "operator": None}, "admin=plant-it,it-ops"),
    ({"viewer": "", "operator": "", "admin": ""}, None),  # the form's empty fields: no mapping, off
    (" Operator = ops ; admin=IT ;", "operator=ops;admin=IT"),
])
def test_the_roles_object_becomes_the_role_text(roles, text):
    config = {"signIn": {"ldap": {"url": "ldap://dir.plant.local", "userBase": "dc=plant", "roles": roles}}}
    if text is None:
        with pytest.raises(ConfigError, match=r"signIn\.ldap\.roles"):  # url set: the roles are needed
            all_env(config)
        return
    env = all_env(config)
    assert env["LIFECYCLE_LDAP_ROLES"] == text
    assert site_sign_in.role_mapping("LIFECYCLE_LDAP_ROLES", env)  # the site reads it


OIDC_ON = {"clientId": "lifecycle", "clientSecret": "x", "authorizationUrl": f"{IDP}/auth",
           "tokenUrl": f"{IDP}/token", "userinfoUrl": f"{IDP}/userinfo", "jwksUrl": f"{IDP}/certs",
           "roles": "admin=plant-it"}
LDAP_ON = {"url": "ldaps://dir.plant.local", "userBase": "dc=plant", "roles": "admin=plant-it"}


@pytest.mark.parametrize("config, key", [
    ({"site": {"language": "fr"}}, "site.language"),
    ({"site": {"language": "english"}}, "site.language"),
    ({"signIn": {"oidc": {**OIDC_ON, "tokenUrl": "ftp://idp.plant.local/token"}}}, "signIn.oidc.tokenUrl"),
    ({"signIn": {"oidc": {**OIDC_ON, "jwksUrl": "idp.plant.local/certs"}}}, "signIn.oidc.jwksUrl"),
    ({"signIn": {"oidc": {**OIDC_ON, "logoutUrl": "javascript:alert(1)"}}}, "signIn.oidc.logoutUrl"),
    ({"signIn": {"oidc": {**OIDC_ON, "issuerUrl": "idp.plant.local"}}}, "signIn.oidc.issuerUrl"),
    ({"signIn": {"ldap": {**LDAP_ON, "url": "https://dir.plant.local"}}}, "signIn.ldap.url"),
    ({"signIn": {"ldap": {**LDAP_ON, "url": "ldaps://a.plant:636,ldap://b.plant:389"}}}, "signIn.ldap.url"),
    ({"signIn": {"oidc": {**OIDC_ON, "roles": "superuser=plant-it"}}}, "signIn.oidc.roles"),
    ({"signIn": {"ldap": {**LDAP_ON, "roles": {"owner": ["plant-it"]}}}}, "signIn.ldap.roles"),
    ({"signIn": {"ldap": {**LDAP_ON, "roles": "plant-it"}}}, "signIn.ldap.roles"),
    ({"signIn": {"ldap": {**LDAP_ON, "roles": {"admin": ["IT"], "viewer": ["it"]}}}}, "signIn.ldap.roles"),
    ({"signIn": {"ldap": {**LDAP_ON, "roles": ["admin=plant-it"]}}}, "signIn.ldap.roles"),
    ({"signIn": {"oidc": {**OIDC_ON, "caCertificate": "MIIBszCCAVmgAwIBAgIU"}}}, "signIn.oidc.caCertificate"),
    ({"signIn": {"ldap": {**LDAP_ON, "caCertificate": "/etc/ssl/plant-ca.pem"}}}, "signIn.ldap.caCertificate"),
    ({"signIn": {"oidc": {k: v for k, v in OIDC_ON.items() if k != "tokenUrl"}}}, "signIn.oidc.tokenUrl"),
    ({"signIn": {"ldap": {"url": "ldaps://dir.plant.local", "roles": "admin=it"}}}, "signIn.ldap.userBase"),
    ({"signIn": {"sessionHours": 0}}, "signIn.sessionHours"),
    ({"signIn": {"sessionHours": "a shift"}}, "signIn.sessionHours"),
    ({"signIn": {"sessionHours": 337}}, "signIn.sessionHours"),
    ({"signIn": {"sessionHours": True}}, "signIn.sessionHours"),
    ({"signIn": {"sessionHours": float("nan")}}, "signIn.sessionHours"),
    ({"signIn": {"tokenDays": 0}}, "signIn.tokenDays"),
    ({"signIn": {"tokenDays": "a month"}}, "signIn.tokenDays"),
    ({"signIn": {"tokenDays": 3651}}, "signIn.tokenDays"),
    ({"signIn": {"tokenDays": False}}, "signIn.tokenDays"),
])
def test_what_cannot_work_is_refused_naming_the_key(config, key, monkeypatch, tmp_path, ca_files):
    with pytest.raises(ConfigError) as refused:
        all_env(read(monkeypatch, tmp_path, config), write_files=True)
    assert key in str(refused.value)
    assert not any(path.exists() for path in ca_files)


def test_the_language_message_names_the_choices():
    with pytest.raises(ConfigError, match=r"site\.language 'fr' must be one of en, de"):
        all_env({"site": {"language": "fr"}})
    assert all_env({"site": {"language": "en"}}) == {"LIFECYCLE_LANGUAGE": "en"}


@pytest.mark.parametrize("config, says", [
    ({"signIn": "ldaps://dir.plant.local"}, "'signIn' must be an object"),
    ({"signIn": {"oidc": ["lifecycle"]}}, "'signIn.oidc' must be an object"),
    ({"signIn": {"ldap": "ldaps://dir.plant.local"}}, "'signIn.ldap' must be an object"),
])
def test_read_config_checks_the_sign_in_parts_are_objects(config, says, monkeypatch, tmp_path):
    with pytest.raises(ConfigError, match=says):
        read(monkeypatch, tmp_path, config)


def test_the_issuer_stands_for_the_four_endpoints(monkeypatch):
    by_issuer = {k: v for k, v in OIDC_ON.items() if not k.endswith("Url")}
    env = all_env({"signIn": {"oidc": {**by_issuer, "issuerUrl": f"{IDP}/"}}})
    assert env["LIFECYCLE_OIDC_ISSUER"] == f"{IDP}/" and "LIFECYCLE_OIDC_TOKEN_URL" not in env
    assert site_sign_in.oidc_settings(env)["OIDC_OP_ISSUER"] == IDP  # the site reads it
    with pytest.raises(ConfigError, match=r"signIn\.oidc\.authorizationUrl.*or signIn\.oidc\.issuerUrl instead"):
        all_env({"signIn": {"oidc": by_issuer}})


def test_what_the_environment_gives_completes_the_configuration(monkeypatch):
    """The secret in docker/.env or the environment, the rest in param.json: accepted, and the
    environment's secret stays in force (nothing is exported for it)."""
    monkeypatch.setenv("LIFECYCLE_OIDC_CLIENT_SECRET", "from-the-environment")
    oidc = {k: v for k, v in OIDC_ON.items() if k != "clientSecret"}
    env = all_env({"signIn": {"oidc": oidc}})
    assert env["LIFECYCLE_OIDC_CLIENT_ID"] == "lifecycle" and "LIFECYCLE_OIDC_CLIENT_SECRET" not in env


def test_the_ca_files_are_written_only_with_write_files(ca_files):
    oidc_ca, ldap_ca = ca_files
    env = all_env(full_config())
    assert env["LIFECYCLE_OIDC_CA_FILE"] == str(oidc_ca) and env["LIFECYCLE_LDAP_CA_FILE"] == str(ldap_ca)
    assert not oidc_ca.exists() and not ldap_ca.exists()
    assert all_env(full_config(), write_files=True) == env
    assert oidc_ca.read_text() == PEM + "\n" and ldap_ca.read_text() == PEM + "\n"


def run_env(role: str, config: dict, tmp_path: Path) -> subprocess.CompletedProcess:
    """docker/runtime/config.py env ROLE, as entrypoint.sh runs it in a container."""
    path = tmp_path / "param.json"
    path.write_text(json.dumps(config))
    environment = {k: v for k, v in os.environ.items() if not k.startswith(("DJANGO_", "LIFECYCLE_", "ROS_"))}
    environment.update(LIFECYCLE_CONFIG_FILE=str(path),
                       LIFECYCLE_CONFIG_OIDC_CA_FILE=str(tmp_path / role / "oidc-ca.crt"),
                       LIFECYCLE_CONFIG_LDAP_CA_FILE=str(tmp_path / role / "ldap-ca.crt"))
    return subprocess.run([sys.executable, str(RUNTIME / "config.py"), "env", role],
                          capture_output=True, text=True, timeout=60, env=environment)


def exported(result: subprocess.CompletedProcess) -> dict[str, str]:
    return dict(shlex.split(line)[1].split("=", 1) for line in result.stdout.splitlines())


@pytest.mark.parametrize("role", ["web", "manage"])
def test_the_containers_that_sign_people_in_get_the_settings_and_ca_files(role, tmp_path):
    result = run_env(role, full_config(), tmp_path)
    assert result.returncode == 0, result.stderr
    env = exported(result)
    assert env["LIFECYCLE_LANGUAGE"] == "de"
    for name, file in (("LIFECYCLE_OIDC_CA_FILE", "oidc-ca.crt"), ("LIFECYCLE_LDAP_CA_FILE", "ldap-ca.crt")):
        assert env[name] == str(tmp_path / role / file)
        assert (tmp_path / role / file).read_text() == PEM + "\n"
    assert "s3cret-Value" not in result.stderr and "b1nd pw" not in result.stderr


@pytest.mark.parametrize("role", ["ingest", "gateway"])
def test_the_sign_in_secrets_stay_out_of_the_containers_that_sign_nobody_in(role, tmp_path):
    result = run_env(role, full_config(), tmp_path)
    assert result.returncode == 0, result.stderr
    env = exported(result)
    assert env["LIFECYCLE_LANGUAGE"] == "de"  # e-mails (ingest) are in the site's language
    assert not [name for name in env if name.startswith(("LIFECYCLE_OIDC_", "LIFECYCLE_LDAP_"))]
    assert "s3cret-Value" not in result.stdout and "b1nd pw" not in result.stdout


def test_a_bad_sign_in_part_stops_the_container_with_the_reason(tmp_path):
    config = full_config()
    config["signIn"]["ldap"]["url"] = "http://dir.plant.local"
    result = run_env("web", config, tmp_path)
    assert result.returncode == 78 and "signIn.ldap.url" in result.stderr, result.stderr


def test_config_env_imports_neither_django_nor_the_site():
    code = ("import sys; sys.path.insert(0, sys.argv[1]); import config_env, sign_in_env; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('django', 'lifecycle_site')))")
    result = subprocess.run([sys.executable, "-c", code, str(RUNTIME)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and result.stdout.strip() == "[]", result.stderr
