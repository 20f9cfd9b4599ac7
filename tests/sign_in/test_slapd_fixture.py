"""The test directory (tests/sign_in/slapd.py) does what sign-in tests rely on: users bind with
their own password over StartTLS and LDAPS (certificate checked against the test CA), their
groups are found by member, a wrong password is refused, and the directory can be taken away
and brought back."""
from __future__ import annotations

import ssl

import ldap3
import pytest
from ldap3.core.exceptions import LDAPInvalidCredentialsResult, LDAPSocketOpenError

from tests import stack
from tests.sign_in.slapd import Directory, start_directory


@pytest.fixture
def directory(tmp_path):
    started = start_directory(tmp_path / "ldap")
    yield started
    started.stop()


def bind(directory: Directory, dn: str, password: str, *, over_ldaps: bool = False) -> ldap3.Connection:
    """A connection bound as ``dn``: StartTLS on the plain port, or LDAPS; the server's certificate
    checked against the test CA either way."""
    tls = ldap3.Tls(validate=ssl.CERT_REQUIRED, ca_certs_file=directory.ca_file)
    if over_ldaps:
        server = ldap3.Server(directory.tls_url, tls=tls, connect_timeout=5)
        auto_bind = ldap3.AUTO_BIND_NO_TLS
    else:
        server = ldap3.Server(directory.url, tls=tls, connect_timeout=5)
        auto_bind = ldap3.AUTO_BIND_TLS_BEFORE_BIND
    return ldap3.Connection(server, dn, password, auto_bind=auto_bind, receive_timeout=5, raise_exceptions=True)


def test_users_bind_find_their_groups_and_the_directory_comes_back_after_a_stop(directory):
    dn = directory.add_user("olga", "olga's password", groups=["lifecycle-operators"], mail="olga@plant.example",
                            given_name="Olga", surname="Operator")
    assert dn == "uid=olga,ou=people,dc=plant,dc=example"

    with bind(directory, dn, "olga's password") as connection:
        assert connection.tls_started
        connection.search(directory.groups, f"(&(objectClass=groupOfNames)(member={dn}))", attributes=["cn"])
        assert [entry.cn.value for entry in connection.entries] == ["lifecycle-operators"]
        connection.search(dn, "(objectClass=inetOrgPerson)", ldap3.BASE, attributes=["mail", "userPassword"])
        assert connection.entries[0].mail.value == "olga@plant.example"
        assert not connection.response[0]["raw_attributes"].get("userPassword")  # nobody reads it
    with bind(directory, dn, "olga's password", over_ldaps=True) as connection:
        assert connection.server.ssl
        assert connection.extend.standard.who_am_i() == f"dn:{dn}"

    with pytest.raises(LDAPInvalidCredentialsResult):
        bind(directory, dn, "not olga's password")
    anonymous = ldap3.Connection(ldap3.Server(directory.url, connect_timeout=5), auto_bind=ldap3.AUTO_BIND_NO_TLS,
                                 receive_timeout=5)
    anonymous.search(directory.base, "(objectClass=*)")
    assert anonymous.entries == []  # anonymous may only bind
    anonymous.unbind()

    directory.stop()
    assert not stack.listens(directory.port) and not stack.listens(directory.tls_port)
    with pytest.raises(LDAPSocketOpenError):
        bind(directory, dn, "olga's password")
    directory.stop()  # a second stop does nothing

    directory.start()
    with bind(directory, dn, "olga's password") as connection:
        assert connection.bound
