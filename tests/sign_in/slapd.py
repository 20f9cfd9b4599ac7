"""A real OpenLDAP directory for sign-in tests: Debian's slapd on two free loopback ports (plain
LDAP with StartTLS, and LDAPS), with a test CA made by openssl, an mdb database under a work
directory, and ACLs as a real directory would have (users bind with their own password and read
people and groups; anonymous may only bind).

``start_directory(workdir)`` makes and starts it; ``Directory.add_user`` adds users and their
groups; ``Directory.stop()``/``start()`` take it away and bring it back on the same ports and data.
slapd runs in its own session and gets SIGKILL when the test process dies (``tests.stack.Process``).
"""
from __future__ import annotations

import base64
import hashlib
import os
import secrets
import shutil
import signal
import ssl
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import ldap3
from ldap3.core.exceptions import LDAPException, LDAPNoSuchObjectResult
from ldap3.utils.dn import escape_rdn

from tests import stack

SLAPD = Path("/usr/sbin/slapd")
MODULE_DIR = Path("/usr/lib/ldap")
SCHEMA_DIR = Path("/etc/ldap/schema")
HOST = "127.0.0.1"
BASE = "dc=plant,dc=example"
START_TIMEOUT = 10.0  # seconds for slapd to answer after it is started
STOP_TIMEOUT = 5.0  # seconds for slapd to end on SIGTERM before it gets SIGKILL
OPERATION_TIMEOUT = 5  # seconds for each connection and request add_user makes
OPENSSL_TIMEOUT = 30


class DirectoryError(RuntimeError):
    """The test directory could not be made or started; the message says why."""


@dataclass
class Directory:
    host: str
    port: int  # plain LDAP, StartTLS offered
    tls_port: int  # LDAPS
    ca_file: str  # the test CA that signed the server's certificate (CN and IP SAN 127.0.0.1)
    base: str
    people: str
    groups: str
    workdir: Path
    admin_dn: str  # slapd's rootdn: not subject to the ACLs
    admin_password: str = field(repr=False)
    _process: stack.Process | None = field(default=None, init=False, repr=False)

    @property
    def url(self) -> str:
        return f"ldap://{self.host}:{self.port}"

    @property
    def tls_url(self) -> str:
        return f"ldaps://{self.host}:{self.tls_port}"

    @property
    def log_path(self) -> Path:
        """slapd's output (all its starts append to it)."""
        return self.workdir / "slapd.log"

    def running(self) -> bool:
        return self._process is not None and self._process.alive()

    def start(self) -> None:
        """Start slapd on this directory's ports and data, and wait (bounded) until it answers."""
        assert self._process is None, "the test directory is already running"
        # -d keeps slapd in the foreground. "-d none", not "-d 0": with 0 slapd prints nothing at
        # all, not even why it could not start (a port in use, a bad config line).
        self._process = stack.Process(
            "slapd",
            [str(SLAPD), "-d", "none", "-f", str(self.workdir / "slapd.conf"),
             "-h", f"ldap://{self.host}:{self.port}/ ldaps://{self.host}:{self.tls_port}/"],
            dict(os.environ), self.workdir,
        )
        try:
            self._wait_until_it_answers()
        except BaseException:
            self.stop()
            raise

    def stop(self) -> None:
        """End slapd: SIGTERM, SIGKILL if it has not ended within STOP_TIMEOUT. Does nothing if
        it is not running."""
        if self._process is not None:
            self._process.stop(signal.SIGTERM, timeout=STOP_TIMEOUT)
            self._process = None

    def add_user(
        self,
        uid: str,
        password: str,
        *,
        groups: Sequence[str] = (),
        mail: str = "",
        given_name: str = "",
        surname: str = "",
    ) -> str:
        """Add an inetOrgPerson ``uid=<uid>`` under people, and make it a member of each of the
        groupOfNames ``cn=<name>`` under groups (a group is created when missing). Returns its DN."""
        dn = f"uid={escape_rdn(uid)},{self.people}"
        attributes = {
            "uid": uid,
            "cn": " ".join(part for part in (given_name, surname) if part) or uid,
            "sn": surname or uid,  # required by person
            "userPassword": ssha(password),
        }
        if mail:
            attributes["mail"] = mail
        if given_name:
            attributes["givenName"] = given_name
        with self._admin_connection() as connection:
            connection.add(dn, ["inetOrgPerson"], attributes)
        for name in groups:
            self.join_group(dn, name)
        return dn

    def join_group(self, member: str, name: str) -> str:
        """Make ``member`` (a user's DN, or a group's: groups within groups) a member of the
        groupOfNames ``cn=<name>`` under groups, made when missing. Returns the group's DN."""
        group = f"cn={escape_rdn(name)},{self.groups}"
        with self._admin_connection() as connection:
            try:
                connection.modify(group, {"member": [(ldap3.MODIFY_ADD, [member])]})
            except LDAPNoSuchObjectResult:
                # A groupOfNames cannot be empty: the group is made with its first member.
                connection.add(group, ["groupOfNames"], {"cn": name, "member": [member]})
        return group

    def leave_group(self, dn: str, name: str) -> None:
        """Take ``dn`` out of the group ``cn=<name>`` (a group left without members is deleted)."""
        group = f"cn={escape_rdn(name)},{self.groups}"
        with self._admin_connection() as connection:
            connection.search(group, "(objectClass=groupOfNames)", ldap3.BASE, attributes=["member"])
            members = [str(m) for m in connection.entries[0].member.values]
            if members == [dn]:
                connection.delete(group)
            else:
                connection.modify(group, {"member": [(ldap3.MODIFY_DELETE, [dn])]})

    def delete(self, dn: str) -> None:
        """Remove the entry ``dn`` (a user who left; their group memberships are left as they are)."""
        with self._admin_connection() as connection:
            connection.delete(dn)

    @property
    def pid(self) -> int:
        assert self._process is not None, "the test directory is not running"
        return self._process.pid

    def _admin_connection(self, over_ldaps: bool = False) -> ldap3.Connection:
        """A connection bound as the rootdn, over plain LDAP (loopback) or LDAPS with the server's
        certificate checked against the test CA; bounded by OPERATION_TIMEOUT."""
        if over_ldaps:
            tls = ldap3.Tls(validate=ssl.CERT_REQUIRED, ca_certs_file=self.ca_file)
            server = ldap3.Server(self.host, port=self.tls_port, use_ssl=True, tls=tls, get_info=ldap3.NONE,
                                  connect_timeout=OPERATION_TIMEOUT)
        else:
            server = ldap3.Server(self.host, port=self.port, get_info=ldap3.NONE, connect_timeout=OPERATION_TIMEOUT)
        return ldap3.Connection(
            server, self.admin_dn, self.admin_password, auto_bind=ldap3.AUTO_BIND_NO_TLS,
            receive_timeout=OPERATION_TIMEOUT, raise_exceptions=True,
        )

    def _wait_until_it_answers(self) -> None:
        assert self._process is not None
        deadline = time.monotonic() + START_TIMEOUT
        last_error: Exception | None = None
        while True:
            if not self._process.alive():
                raise DirectoryError(
                    f"slapd ended as it started (exit {self._process.popen.returncode}); its log, {self.log_path}:\n"
                    f"{_tail(self.log_path)}"
                )
            try:
                self._admin_connection().unbind()
                self._admin_connection(over_ldaps=True).unbind()
                return
            except LDAPException as exc:
                last_error = exc
            if time.monotonic() > deadline:
                detail = f" (last error: {last_error})" if last_error else ""
                raise DirectoryError(
                    f"slapd did not answer on {self.url} and {self.tls_url} within {START_TIMEOUT:g} s{detail}; "
                    f"its log, {self.log_path}:\n{_tail(self.log_path)}"
                )
            time.sleep(0.1)


def start_directory(workdir: Path) -> Directory:
    """Make a directory for ``dc=plant,dc=example`` in ``workdir`` (certificates, slapd.conf,
    database) and start it, with the base, ``ou=people`` and ``ou=groups`` in it."""
    if not SLAPD.exists() or not (MODULE_DIR / "back_mdb.so").exists():
        raise DirectoryError(f"Debian's slapd is needed (apt-get install slapd ldap-utils): no {SLAPD} "
                             f"or {MODULE_DIR / 'back_mdb.so'}")
    if shutil.which("openssl") is None:
        raise DirectoryError("openssl is needed to make the test directory's certificates (apt-get install openssl)")
    workdir.mkdir(parents=True, exist_ok=True)
    ca_file, cert_file, key_file = _make_certificates(workdir)
    port = stack.free_port()
    tls_port = stack.free_port()
    while tls_port == port:
        tls_port = stack.free_port()
    directory = Directory(
        host=HOST, port=port, tls_port=tls_port, ca_file=str(ca_file), base=BASE,
        people=f"ou=people,{BASE}", groups=f"ou=groups,{BASE}", workdir=workdir,
        admin_dn=f"cn=admin,{BASE}", admin_password=secrets.token_urlsafe(24),
    )
    (workdir / "data").mkdir(exist_ok=True)
    config = workdir / "slapd.conf"
    config.write_text(_config(directory, cert_file, key_file))
    config.chmod(0o600)  # it holds the rootdn's password hash
    directory.start()
    try:
        with directory._admin_connection() as connection:
            connection.add(BASE, ["dcObject", "organization"], {"dc": "plant", "o": "Plant"})
            connection.add(directory.people, ["organizationalUnit"], {"ou": "people"})
            connection.add(directory.groups, ["organizationalUnit"], {"ou": "groups"})
    except BaseException:
        directory.stop()
        raise
    return directory


def ssha(password: str) -> str:
    """``password`` as slapd's salted SHA-1 ({SSHA}) userPassword value."""
    salt = secrets.token_bytes(8)
    digest = hashlib.sha1(password.encode() + salt).digest()
    return "{SSHA}" + base64.b64encode(digest + salt).decode()


def _make_certificates(workdir: Path) -> tuple[Path, Path, Path]:
    """A test CA, and a server certificate for 127.0.0.1 (CN and IP subjectAltName) it signed."""
    ca_key, ca_file, key_file, request, cert_file = (
        workdir / name for name in ("ca.key", "ca.crt", "server.key", "server.csr", "server.crt"))
    extensions = workdir / "server-extensions.cnf"
    extensions.write_text(
        "basicConstraints = CA:FALSE\nkeyUsage = critical, digitalSignature, keyEncipherment\n"
        "extendedKeyUsage = serverAuth\nsubjectAltName = IP:127.0.0.1\n"
        "subjectKeyIdentifier = hash\nauthorityKeyIdentifier = keyid\n"
    )
    new_key = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
    commands = [
        ["openssl", "req", "-x509", *new_key, "-days", "2", "-subj", "/CN=lifecycle test LDAP CA",
         "-addext", "basicConstraints=critical,CA:TRUE", "-addext", "keyUsage=critical,keyCertSign,cRLSign",
         "-keyout", ca_key, "-out", ca_file],
        ["openssl", "req", *new_key, "-subj", f"/CN={HOST}", "-keyout", key_file, "-out", request],
        ["openssl", "x509", "-req", "-in", request, "-CA", ca_file, "-CAkey", ca_key, "-CAcreateserial",
         "-days", "2", "-extfile", extensions, "-out", cert_file],
    ]
    for argv in commands:
        done = subprocess.run([str(a) for a in argv], capture_output=True, text=True, timeout=OPENSSL_TIMEOUT)
        if done.returncode != 0:
            raise DirectoryError(f"openssl failed making the test directory's certificates: {argv[:2]}:\n"
                                 f"{done.stdout}{done.stderr}")
    key_file.chmod(0o600)
    return ca_file, cert_file, key_file


def _config(directory: Directory, cert_file: Path, key_file: Path) -> str:
    """slapd.conf (the classic config file, not cn=config) for ``directory``."""
    schemas = "\n".join(f"include {SCHEMA_DIR / name}.schema" for name in ("core", "cosine", "inetorgperson"))
    workdir = directory.workdir
    # Access is decided by the first "access to" whose target matches. userPassword: anonymous
    # may use it to bind (auth), nobody may read it. Everything else in the base: bound users
    # read. The root DSE and the schema (which ldap3 reads after a bind) likewise. The rootdn
    # is not subject to these rules.
    return f"""\
modulepath {MODULE_DIR}
moduleload back_mdb
{schemas}

pidfile {workdir / "slapd.pid"}
argsfile {workdir / "slapd.args"}

TLSCACertificateFile {directory.ca_file}
TLSCertificateFile {cert_file}
TLSCertificateKeyFile {key_file}

access to dn.base="" by users read by * none
access to dn.base="cn=Subschema" by users read by * none

database mdb
suffix "{directory.base}"
rootdn "{directory.admin_dn}"
rootpw {ssha(directory.admin_password)}
directory {workdir / "data"}
maxsize 67108864
index objectClass eq
index uid eq
index member eq

access to attrs=userPassword
    by anonymous auth
    by * none
access to dn.subtree="{directory.base}"
    by users read
    by * none
"""


def _tail(path: Path, lines: int = 40) -> str:
    if not path.exists():
        return "(no log)"
    return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
