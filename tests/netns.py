"""Test hosts made of Linux network namespaces: switches, hosts, routers, and one private link
from the root namespace to the site's host, for multi-host tests on one machine.

A ``Fabric`` owns everything it makes and removes it on ``close()`` (also a context manager):
the processes it started, its namespaces (which takes their links along) and its one veth end
in the root namespace. Names carry the pid of the test run (``lcn<pid>-...``), so a run never
touches another's; ``remove_leftovers()`` clears what a run that died without cleaning up left
behind (namespaces and links of a pid that no longer runs), and every fabric still open when the
process exits is closed by an ``atexit`` handler.

* A switch is a namespace with a Linux bridge ``br0`` (never a bridge of the root namespace).
* A host is a namespace where processes run with ``ip netns exec``; ``plug`` gives it an
  interface on a switch (``eth0``, ``eth1``, ...) with an address you choose.
* A router is a host with ``ip_forward`` on and a leg on each of its switches.
* ``uplink`` links the root namespace to one host (the site's host) by a veth pair with a /30 of
  10.231.0.0/24 on it: the root namespace gets that one address (IPv6 and multicast off on it)
  and nothing else; nothing is forwarded to or from it. The site host has no route beyond its
  own links, and hosts reach it through routes you add, so DDS traffic (multicast above all)
  never reaches the root namespace.

Everything here needs root (``ip netns``, ``ebtables``).
"""
from __future__ import annotations

import atexit
import ipaddress
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from ros_gateway.shared.child_process import die_with_parent
from tests import stack

PREFIX = "lcn"
NAME = re.compile(rf"^{PREFIX}(\d+)-")
ROOT_LINK = re.compile(rf"^{PREFIX}(\d+)u\d+$")
UPLINK_NET = ipaddress.ip_network("10.231.0.0/24")
# Every address the fabrics use. While a fabric exists, the root namespace has an "unreachable"
# route for all of it: a packet for a test host that is not on the one uplink (a stale DDS
# locator, say) is dropped here instead of taking the default route out of a real interface.
FABRIC_NET = "10.231.0.0/16"

_open: list["Fabric"] = []
_count = 0


class NetError(RuntimeError):
    """An ``ip``/``ebtables``/``sysctl`` command failed; the message has the command and its stderr."""


def run(*argv: str, check: bool = True, timeout: float = 20, env: dict[str, str] | None = None
        ) -> subprocess.CompletedProcess:
    done = subprocess.run(list(argv), capture_output=True, text=True, timeout=timeout, env=env)
    if check and done.returncode != 0:
        raise NetError(f"{' '.join(argv)} exited {done.returncode}: {done.stderr.strip() or done.stdout.strip()}")
    return done


def ip(*args: str, ns: str | None = None, check: bool = True) -> subprocess.CompletedProcess:
    return run("ip", *(("-n", ns) if ns else ()), *args, check=check)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def namespaces() -> list[str]:
    out = run("ip", "netns", "list", check=False).stdout
    return [line.split()[0] for line in out.splitlines() if line.strip()]


def root_links() -> list[str]:
    out = ip("-o", "link", "show", check=False).stdout
    return [m.group(1).split("@")[0] for m in re.finditer(r"^\d+:\s+(\S+):", out, re.M)]


def _kill_inside(ns: str) -> None:
    """Every process still running in namespace ``ns`` (all of them started by a fabric)."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        pids = [int(p) for p in run("ip", "netns", "pids", ns, check=False).stdout.split()]
        if not pids:
            return
        for pid in pids:
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + 3
        while time.monotonic() < deadline and run("ip", "netns", "pids", ns, check=False).stdout.split():
            time.sleep(0.05)


def remove_namespace(ns: str) -> None:
    _kill_inside(ns)
    run("ip", "netns", "del", ns, check=False)


def ours(pid: int | None = None) -> tuple[list[str], list[str]]:
    """Namespaces and root links of the run with ``pid`` (default: this process)."""
    pid = os.getpid() if pid is None else pid
    spaces = [n for n in namespaces() if (m := NAME.match(n)) and int(m.group(1)) == pid]
    links = [n for n in root_links() if (m := ROOT_LINK.match(n)) and int(m.group(1)) == pid]
    return spaces, links


def guard_root(on: bool) -> None:
    """The root namespace's unreachable route for FABRIC_NET (removed when no run uses it)."""
    if on:
        ip("route", "replace", "unreachable", FABRIC_NET)
    elif not any(ROOT_LINK.match(link) for link in root_links()):
        ip("route", "del", "unreachable", FABRIC_NET, check=False)


def remove_leftovers() -> list[str]:
    """Remove the namespaces and root links of earlier runs whose process is gone; returns them."""
    removed = []
    for ns in namespaces():
        m = NAME.match(ns)
        if m and int(m.group(1)) != os.getpid() and not _pid_alive(int(m.group(1))):
            remove_namespace(ns)
            removed.append(ns)
    for link in root_links():
        m = ROOT_LINK.match(link)
        if m and int(m.group(1)) != os.getpid() and not _pid_alive(int(m.group(1))):
            ip("link", "del", link, check=False)
            removed.append(link)
    guard_root(False)
    return removed


class NsProcess(stack.Process):
    """A process in a namespace (``ip netns exec NS argv``; in the root namespace when ``host``
    is None): output to a log file, and it gets SIGTERM should the test run die without
    stopping it."""

    def __init__(self, host: "Host | None", name: str, argv: list[str], env: dict[str, str], log_dir: Path) -> None:
        self.name, self.host = name, host
        self.log_path = log_dir / f"{name}.log"
        log_dir.mkdir(parents=True, exist_ok=True)
        prefix = ["ip", "netns", "exec", host.ns] if host is not None else []
        with open(self.log_path, "ab") as log:
            self.popen = subprocess.Popen(
                [*prefix, *argv], cwd=stack.ROOT, env=env, stdout=log, stderr=subprocess.STDOUT,
                start_new_session=True, preexec_fn=die_with_parent(),
            )

    def tail(self, lines: int = 40) -> str:
        where = self.host.name if self.host is not None else "the root namespace"
        text = self.output().splitlines()[-lines:]
        return f"--- {self.name} on {where} (exit {self.popen.poll()}) ---\n" + "\n".join(text)


class Host:
    """A namespace: interfaces, addresses, routes, processes."""

    def __init__(self, fabric: "Fabric", name: str) -> None:
        self.fabric, self.name = fabric, name
        self.ns = f"{fabric.prefix}{name}"
        self.interfaces: dict[str, str] = {}  # name -> address/prefix
        self.ports: dict[str, tuple[Switch, str]] = {}  # interface -> the switch and port it is plugged into
        run("ip", "netns", "add", self.ns)
        fabric.spaces.append(self.ns)
        ip("link", "set", "lo", "up", ns=self.ns)
        self.sysctl("net.ipv6.conf.all.disable_ipv6", "1")  # DDS here is IPv4; no IPv6 chatter

    def __repr__(self) -> str:
        return f"<host {self.name} {self.address}>"

    @property
    def address(self) -> str:
        """The first interface's address, without the prefix length."""
        return next(iter(self.interfaces.values())).split("/")[0]

    def sysctl(self, key: str, value: str) -> None:
        run("ip", "netns", "exec", self.ns, "sysctl", "-qw", f"{key}={value}")

    def run(self, *argv: str, check: bool = True, timeout: float = 20, env: dict[str, str] | None = None
            ) -> subprocess.CompletedProcess:
        return run("ip", "netns", "exec", self.ns, *argv, check=check, timeout=timeout, env=env)

    def route(self, destination: str, via: str) -> None:
        ip("route", "replace", destination, "via", via, ns=self.ns)

    def cable(self, plugged: bool, interface: str = "eth0") -> None:
        """Pull (or plug back) the cable of ``interface`` at the switch: the host keeps its
        addresses and routes, its interface just loses its carrier."""
        switch, port = self.ports[interface]
        ip("link", "set", port, "up" if plugged else "down", ns=switch.ns)

    def start(self, name: str, argv: list[str], env: dict[str, str], log_dir: Path | None = None) -> NsProcess:
        """``argv`` in this namespace; its output goes to ``log_dir`` (default: the test run's logs)."""
        process = NsProcess(self, name, argv, env, log_dir or stack.log_dir())
        self.fabric.processes.append(process)
        return process


class Switch(Host):
    """A namespace holding one Linux bridge, ``br0``; its ports are named after the hosts."""

    def __init__(self, fabric: "Fabric", name: str, subnet: str) -> None:
        super().__init__(fabric, name)
        self.subnet = ipaddress.ip_network(subnet)
        ip("link", "add", "br0", "type", "bridge", ns=self.ns)
        ip("link", "set", "br0", "up", ns=self.ns)

    def drop_multicast(self) -> None:
        """The switch forwards no multicast frame (IPv4 and IPv6 alike); broadcast (ARP) still passes."""
        self.run("ebtables", "-A", "FORWARD", "-d", "Broadcast", "-j", "ACCEPT")
        self.run("ebtables", "-A", "FORWARD", "-d", "Multicast", "-j", "DROP")


class Fabric:
    def __init__(self, tag: str = "") -> None:
        global _count
        _count += 1
        self.index = _count
        self.prefix = f"{PREFIX}{os.getpid()}-{tag}{self.index}-"
        self.spaces: list[str] = []
        self.processes: list[NsProcess] = []
        self.root_link: str | None = None
        self.hosts: dict[str, Host] = {}
        self._ports: dict[str, int] = {}
        self.closed = False
        if threading.current_thread() is threading.main_thread():
            remove_leftovers()
        _open.append(self)

    def __enter__(self) -> "Fabric":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- building ----------------------------------------------------------------------
    def host(self, name: str) -> Host:
        assert name not in self.hosts, name
        self.hosts[name] = Host(self, name)
        return self.hosts[name]

    def router(self, name: str) -> Host:
        router = self.host(name)
        router.sysctl("net.ipv4.ip_forward", "1")
        return router

    def switch(self, name: str, subnet: str) -> Switch:
        assert name not in self.hosts, name
        self.hosts[name] = Switch(self, name, subnet)
        return self.hosts[name]

    def plug(self, host: Host, switch: Switch, last_octet: int, multicast: bool = True) -> str:
        """A veth from ``host`` (``ethN``) to a port of ``switch`` with the address
        ``switch.subnet``.``last_octet``; returns the address (without prefix length)."""
        interface = f"eth{len(host.interfaces)}"
        port = f"{host.name[:12]}{self._ports.setdefault(switch.name, 0)}"
        self._ports[switch.name] += 1
        # Both ends are made inside their namespaces: nothing ever appears in the root namespace.
        ip("link", "add", "name", interface, "netns", host.ns, "type", "veth", "peer", "name", port,
           "netns", switch.ns)
        address = f"{switch.subnet.network_address + last_octet}/{switch.subnet.prefixlen}"
        ip("addr", "add", address, "dev", interface, ns=host.ns)
        if not multicast:
            ip("link", "set", interface, "multicast", "off", ns=host.ns)
            ip("link", "set", port, "multicast", "off", ns=switch.ns)
        ip("link", "set", port, "master", "br0", "up", ns=switch.ns)
        ip("link", "set", interface, "up", ns=host.ns)
        host.interfaces[interface] = address
        host.ports[interface] = (switch, port)
        return address.split("/")[0]

    def uplink(self, host: Host) -> tuple[str, str]:
        """The one link of the root namespace: a veth from it to ``host`` with a free /30 of
        10.231.0.0/24; returns (root address, host address)."""
        assert self.root_link is None, "one uplink per fabric"
        taken = set()
        for line in ip("-4", "-o", "addr", "show").stdout.splitlines():
            for word in line.split():
                if "/" in word and word[0].isdigit():
                    taken.add(ipaddress.ip_interface(word).network)
        for network in UPLINK_NET.subnets(new_prefix=30):
            if not any(network.overlaps(t) for t in taken):
                break
        else:
            raise NetError("no free /30 left in 10.231.0.0/24 in the root namespace")
        root_address, host_address = (str(a) for a in list(network.hosts())[:2])
        name = f"{PREFIX}{os.getpid()}u{self.index}"
        guard_root(True)
        ip("link", "add", "name", name, "type", "veth", "peer", "name", "uplink", "netns", host.ns)
        self.root_link = name
        for key in ("disable_ipv6",):
            run("sysctl", "-qw", f"net.ipv6.conf.{name}.{key}=1")
        ip("link", "set", name, "multicast", "off")
        ip("link", "set", "uplink", "multicast", "off", ns=host.ns)
        ip("addr", "add", f"{root_address}/30", "dev", name)
        ip("addr", "add", f"{host_address}/30", "dev", "uplink", ns=host.ns)
        ip("link", "set", name, "up")
        ip("link", "set", "uplink", "up", ns=host.ns)
        host.interfaces["uplink"] = f"{host_address}/30"
        return root_address, host_address

    def root_link_counters(self) -> dict:
        """Packets the root namespace's link received, multicast among them."""
        assert self.root_link
        stats = json.loads(ip("-s", "-j", "link", "show", self.root_link).stdout)[0]["stats64"]["rx"]
        return {"packets": stats["packets"], "multicast": stats["multicast"]}

    # -- ending ------------------------------------------------------------------------
    def close(self) -> None:
        """Stop the processes, remove the namespaces and the root link (safe to call twice)."""
        if self.closed:
            return
        self.closed = True
        for process in reversed(self.processes):
            try:
                process.stop(timeout=5)
            except Exception as exc:  # noqa: BLE001 - go on removing the rest
                print(f"netns: stopping {process.name}: {exc}", file=sys.stderr)
        for ns in reversed(self.spaces):
            remove_namespace(ns)
        if self.root_link:
            ip("link", "del", self.root_link, check=False)  # gone with its peer's namespace, normally
            guard_root(False)
        if self in _open:
            _open.remove(self)


def close_all() -> None:
    """Close every fabric of this process still open, and anything of ours left over."""
    for fabric in list(_open):
        fabric.close()
    spaces, links = ours()
    for ns in spaces:
        remove_namespace(ns)
    for link in links:
        ip("link", "del", link, check=False)
    guard_root(False)


atexit.register(close_all)


def udp_probe(sender: Host, receiver: Host, group: str = "239.255.0.1", port: int = 7400,
              wait: float = 1.0) -> dict[str, bool]:
    """Does a UDP datagram from ``sender`` reach ``receiver``: sent to the multicast ``group``
    (the DDS discovery group and port of domain 0) and to the receiver's address? Both are sent
    the way DDS sends them (multicast out of the sender's interface, TTL 1)."""
    listen = (
        "import socket, select\n"
        f"group, port, me = {group!r}, {port}, {receiver.address!r}\n"
        "m = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)\n"
        "m.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)\n"
        "m.bind(('', port))\n"
        "m.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, socket.inet_aton(group) + socket.inet_aton(me))\n"
        "u = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); u.bind((me, port + 1))\n"
        "print('ready', flush=True)\n"
        "got = set()\n"
        f"end = __import__('time').monotonic() + {wait + 1.5}\n"
        "while len(got) < 2 and (left := end - __import__('time').monotonic()) > 0:\n"
        "    for s in select.select([m, u], [], [], left)[0]:\n"
        "        got.add(s.recv(100).decode())\n"
        "print(' '.join(sorted(got)), flush=True)\n"
    )
    listener = subprocess.Popen(["ip", "netns", "exec", receiver.ns, sys.executable, "-c", listen],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert listener.stdout.readline().strip() == "ready", listener.stderr.read()
        send = (
            "import socket\n"
            "s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)\n"
            f"s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton({sender.address!r}))\n"
            "s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)\n"
            "for _ in range(3):\n"
            f"    try: s.sendto(b'multicast', ({group!r}, {port}))\n"
            "    except OSError as e: print('multicast send:', e)\n"
            f"    s.sendto(b'unicast', ({receiver.address!r}, {port + 1}))\n"
        )
        sender.run(sys.executable, "-c", send)
        out, _ = listener.communicate(timeout=wait + 10)
    finally:
        if listener.poll() is None:
            listener.kill()
            listener.wait()
    words = out.split()
    return {"multicast": "multicast" in words, "unicast": "unicast" in words}

