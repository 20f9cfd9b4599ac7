"""Where a webhook may send to (docs/alerts.md, "Where webhooks may go").

The ingest process POSTs to URLs that admins enter, from inside the plant's network: without
a check, a URL could reach this machine's own services, a cloud metadata service or any
internal host. Checked when a receiver is saved and again at every delivery, on the
addresses the name resolves to then; the request goes to the address that was checked.

- Never: unspecified (0.0.0.0, ::), multicast, link-local (169.254.0.0/16, fe80::/10, where
  cloud metadata services answer) and reserved addresses.
- Loopback and this machine's own addresses: only those LIFECYCLE_WEBHOOK_ALLOW lists one by
  one (or a loopback network), not through a wider network or a name.
- Other addresses that are not public (10/8, 172.16/12, 192.168/16, 100.64/10, fc00::/7 ...):
  those in a network the setting lists, or all addresses of a host name it lists.
- Public addresses: always.
"""
from __future__ import annotations

import ipaddress
import re
import socket
from dataclasses import dataclass
from urllib.parse import SplitResult, urlsplit

from django.conf import settings
from django.utils.translation import gettext as _
from django.utils.translation import gettext_lazy


def gettext_noop(text: str) -> str:
    """Marks ``text`` for the catalogue (makemessages knows the name). Django's own gettext_noop
    reads the settings, which are not loaded yet when settings.py calls parse_allow."""
    return text

IPAddress = ipaddress.IPv4Address | ipaddress.IPv6Address
IPNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network
SETTING = "LIFECYCLE_WEBHOOK_ALLOW"
LOOPBACK = (ipaddress.ip_network("127.0.0.0/8"), ipaddress.ip_network("::1/128"))
NAT64 = ipaddress.ip_network("64:ff9b::/96")
HOST_NAME = re.compile(r"(?=.{1,253}$)([a-z0-9]([a-z0-9-]{0,61}[a-z0-9])?)(\.[a-z0-9]([a-z0-9-]{0,61}[a-z0-9])?)*")
CREDENTIALS = gettext_lazy("a user name or password in the URL is not accepted (it would be shown in the admin and "
                           "sent as plain Basic authentication); a receiver proves a request is ours by its "
                           "signature: set the receiver's secret and check X-Lifecycle-Signature")


class Refused(ValueError):
    """This URL may not be used; the message says why, in words for the admin (in the active
    language: a delivery makes it with English active, for the delivery log)."""


@dataclass(frozen=True)
class Allow:
    """LIFECYCLE_WEBHOOK_ALLOW, parsed: networks (single addresses as /32 or /128) and host names."""

    networks: tuple[IPNetwork, ...] = ()
    names: frozenset[str] = frozenset()


@dataclass(frozen=True)
class Target:
    """A checked URL: where to connect (the checked addresses) and what to ask for."""

    scheme: str
    host: str  # as in the URL: the Host header and the TLS server name
    port: int
    path: str  # with its query
    addresses: tuple[str, ...]


# (Marked, not translated here: parse_allow reads them while the settings load, in English.)
_NEVER = tuple((ipaddress.ip_network(network), why) for network, why in (
    ("0.0.0.0/8", gettext_noop("an unspecified address (this machine)")),
    ("::/128", gettext_noop("an unspecified address (this machine)")),
    ("224.0.0.0/4", gettext_noop("a multicast address")), ("ff00::/8", gettext_noop("a multicast address")),
    ("169.254.0.0/16", gettext_noop("a link-local address, where cloud metadata services answer")),
    ("fe80::/10", gettext_noop("a link-local address, where cloud metadata services answer")),
    ("fd00:ec2::254/128", gettext_noop("a cloud metadata address")),  # AWS's IPv6 one is not link-local
    ("240.0.0.0/4", gettext_noop("a reserved address")),  # 255.255.255.255 included
))


def never_allowed(address: IPAddress) -> str:
    """Why no setting opens this address, or '' (in English: refusal() translates it)."""
    return next((why for network, why in _NEVER if address in network), "")


def parse_allow(text: str) -> Allow:
    """The setting's value: comma-separated addresses, networks and host names. Raises
    ValueError naming the entry that is not one."""
    networks, names = [], set()
    for entry in filter(None, (part.strip() for part in text.split(","))):
        try:
            network = ipaddress.ip_network(entry)  # strict: 10.20.0.1/16 is a mistake, not 10.20.0.0/16
        except ValueError as exc:
            name = entry.lower().rstrip(".")
            if "has host bits set" in str(exc):
                raise ValueError(f"{entry!r} has host bits set; write the network, e.g. "
                                 f"{ipaddress.ip_network(entry, strict=False)}") from None
            if not HOST_NAME.fullmatch(name) or name.replace(".", "").isdigit():
                raise ValueError(f"{entry!r} is not an address, a network (10.20.0.0/16) or a host name "
                                 "(tickets.plant); no schemes, ports or wildcards") from None
            names.add(name)
            continue
        # (0.0.0.0/0 may be listed: the parts of it that are never allowed stay shut)
        why = next((why for never, why in _NEVER if never.version == network.version and network.subnet_of(never)), "")
        if why:
            raise ValueError(f"{entry!r} is {why}: webhooks never go there")
        networks.append(network)
    return Allow(tuple(networks), frozenset(names))


def _unmapped(address: IPAddress) -> IPAddress:
    """::ffff:127.0.0.1 is 127.0.0.1 (Python 3.11's properties do not look through it), and so
    is 64:ff9b::7f00:1, which a NAT64 gateway would turn into it."""
    if isinstance(address, ipaddress.IPv6Address):
        if address.ipv4_mapped is not None:
            return address.ipv4_mapped
        if address in NAT64:
            return ipaddress.IPv4Address(int(address) & 0xFFFFFFFF)
    return address


def own_addresses() -> set[IPAddress]:
    """This machine's addresses (in its network namespace, Linux): every local IPv4 address of
    the kernel's routing table, every IPv6 address of an interface."""
    found: set[IPAddress] = set()
    try:
        with open("/proc/net/fib_trie") as table:  # '|-- 10.1.2.3' then '/32 host LOCAL'
            previous = ""
            for line in table:
                if "host LOCAL" in line and previous.startswith("|--"):
                    found.add(ipaddress.ip_address(previous[3:].strip()))
                previous = line.strip()
    except OSError:
        pass
    try:
        with open("/proc/net/if_inet6") as table:
            for line in table:
                found.add(ipaddress.IPv6Address(int(line.split()[0], 16)))
    except OSError:
        pass
    return found


def refusal(address: IPAddress, host: str, allow: Allow, own: set[IPAddress]) -> str:
    """Why a webhook may not go to this address (``host`` resolved to it), or ''."""
    address = _unmapped(address)
    if why := never_allowed(address):
        return _("%(why)s; webhooks never go there") % {"why": _(why)}
    listed = any(n.num_addresses == 1 and address in n for n in allow.networks)
    if address.is_loopback:
        if listed or any(address in n and any(n.subnet_of(lo) for lo in LOOPBACK if lo.version == n.version)
                         for n in allow.networks):
            return ""
        return _("a loopback address (this machine); allowed only if %(setting)s lists %(address)s itself") % {
            "setting": SETTING, "address": address}
    if address in own:
        return "" if listed else _("an address of this machine; allowed only if %(setting)s lists %(address)s "
                                   "itself") % {"setting": SETTING, "address": address}
    if address.is_global or host.lower().rstrip(".") in allow.names or any(address in n for n in allow.networks):
        return ""
    if _literal(host):
        return _("an internal address; allowed only if %(setting)s lists it or its network") % {"setting": SETTING}
    return _("an internal address; allowed only if %(setting)s lists it or its network or the host name "
             "%(host)s") % {"setting": SETTING, "host": host}


def _literal(host: str) -> bool:
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True


def redact(url: str) -> str:
    """The URL as it may be shown and logged: a user name or password in it replaced by ***."""
    parts = urlsplit(url)
    if "@" not in parts.netloc:
        return url
    return parts._replace(netloc="***@" + parts.netloc.rpartition("@")[2]).geturl()


def split(url: str) -> tuple[SplitResult, str, int]:
    """The URL's parts, host and port; Refused if it is no http(s) URL or carries credentials."""
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as exc:
        raise Refused(_("not a valid URL: %(error)s") % {"error": exc}) from None
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise Refused(_("not an http:// or https:// URL with a host"))
    if "@" in parts.netloc:
        raise Refused(str(CREDENTIALS))
    return parts, parts.hostname, port or (443 if parts.scheme == "https" else 80)


def resolve(host: str, port: int) -> list[IPAddress]:
    """Every address the host name resolves to (raises OSError when it does not)."""
    found = []
    for *_info, sockaddr in socket.getaddrinfo(host, port, type=socket.SOCK_STREAM):
        address = ipaddress.ip_address(str(sockaddr[0]).partition("%")[0])  # fe80::1%eth0
        if address not in found:
            found.append(address)
    return found


def check(url: str) -> Target:
    """Resolve the URL's host and check every address: the Target to connect to, or Refused.
    OSError when the name does not resolve (worth retrying at delivery)."""
    parts, host, port = split(url)
    allow: Allow = settings.LIFECYCLE_WEBHOOK_ALLOW
    own = own_addresses()
    addresses = resolve(host, port)
    for address in addresses:
        if why := refusal(address, host, allow, own):
            if _literal(host):
                raise Refused(_("%(host)s is %(why)s") % {"host": host, "why": why})
            raise Refused(_("%(host)s resolves to %(address)s, which is %(why)s") % {
                "host": host, "address": address, "why": why})
    path = parts.path or "/"
    return Target(parts.scheme, host, port, f"{path}?{parts.query}" if parts.query else path,
                  tuple(str(a) for a in addresses))


def problem(url: str) -> str:
    """For forms: why this URL cannot be saved, or ''. A name that does not resolve (yet) is
    not a reason: every delivery checks again what it resolves to then."""
    try:
        check(url)
    except Refused as exc:
        return str(exc)
    except OSError:
        pass
    return ""
