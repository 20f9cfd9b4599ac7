"""A stand-in for an Industrial Edge device's layer-2 network, on this machine only.

On a device the operator enables layer-2 access for an interface and the device creates the
Docker macvlan network ``zzz_layer2_net1`` on it: an app's container joins it and becomes a
host of the plant LAN (its own MAC and address). Here the plant LAN is a network namespace
where the robots run (this venv's Python under ``ip netns exec``), joined to the root
namespace by a veth pair; the root namespace's end has no address and no master and is the
macvlan's parent::

    namespace lcl2-<pid>-<tag> ("the plant LAN")       root namespace          containers
      eth0 10.232.0.10/24, robots  <--- veth --->  l2h<pid><tag> (UP, no address)
                                                     `- parent of zzz_layer2_net1 (macvlan, bridge mode)
                                                          eth* 10.232.0.128/25 (Docker's range)

A macvlan child cannot talk to its parent, but nothing talks to the parent here: the robots
sit at the veth's other end, behind it. Multicast (DDS discovery) stays in the namespace, on
the veth and on the macvlan children: the parent has no address, nothing routes from it, and
``sniff`` checks that none of it shows on the machine's real interfaces.

The root namespace gets an ``unreachable`` route for the plant LAN's subnet while it exists:
DDS announces every address of a participant, so a robot *container* on a Docker bridge (the
demo robot) tries the gateway's layer-2 address too, through its default route, the host; the
host would send that on along its own default route, off this machine. On a device this is
the device's routing; here the plant LAN must not be reachable from anywhere but itself.
"""
from __future__ import annotations

import os
import re
import signal
import socket
import struct
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from tests.deploy.engine import ROOT, DeployError, run, wait_for

NETWORK = "zzz_layer2_net1"  # the name the device gives it; apps join it as an external network
SUBNET = "10.232.0.0/24"
IP_RANGE = "10.232.0.128/25"  # what Docker hands out; the robots' addresses lie below it
ROUTER = "10.232.0.1"  # the plant's default gateway as Docker is told; nobody answers there
DDS_MULTICAST = "239.255.0.1"
NAMESPACE_RE = re.compile(r"lcl2-(\d+)-[a-z]")
LINK_RE = re.compile(r"l2h(\d+)[a-z]")


def dds_ports(domain: int) -> range:
    """The UDP ports of a ROS domain (RTPS: 7400 + 250 * domain, 250 of them)."""
    return range(7400 + 250 * domain, 7400 + 250 * (domain + 1))


def _pid_alive(pid: int) -> bool:
    return Path(f"/proc/{pid}").exists()


def namespaces() -> list[str]:
    result = run(["ip", "netns", "list"], timeout=20, check=False)
    return [line.split()[0] for line in result.stdout.splitlines() if line.strip()]


def root_links() -> list[str]:
    return sorted(os.listdir("/sys/class/net"))


def _kill_inside(namespace: str) -> None:
    """Every process in the namespace (ours: robots, probes), TERM then KILL."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        pids = run(["ip", "netns", "pids", namespace], timeout=20, check=False).stdout.split()
        if not pids:
            return
        for pid in pids:
            try:
                os.kill(int(pid), sig)
            except (ProcessLookupError, ValueError):
                pass
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and run(["ip", "netns", "pids", namespace], timeout=20,
                                                   check=False).stdout.split():
            time.sleep(0.2)


def _route(action: str) -> subprocess.CompletedProcess:
    return run(["ip", "route", action, "unreachable", SUBNET], timeout=20, check=False)


def remove_stale() -> list[str]:
    """Plant LANs of earlier runs whose pytest process is gone (killed before its teardown):
    their processes, namespaces, root links and, once no plant LAN is left, the unreachable
    route. (Their macvlan network carries the compose project label of that run and goes with
    remove_stale_projects.)"""
    removed = []
    for namespace in namespaces():
        match = NAMESPACE_RE.fullmatch(namespace)
        if match and not _pid_alive(int(match.group(1))):
            _kill_inside(namespace)
            run(["ip", "netns", "delete", namespace], timeout=20, check=False)
            removed.append(namespace)
    for link in root_links():
        match = LINK_RE.fullmatch(link)
        if match and not _pid_alive(int(match.group(1))):
            run(["ip", "link", "delete", link], timeout=20, check=False)
            removed.append(link)
    if not any(NAMESPACE_RE.fullmatch(n) for n in namespaces()) and _route_present():
        _route("del")
        removed.append(f"route unreachable {SUBNET}")
    return removed


def _route_present() -> bool:
    return SUBNET in run(["ip", "route", "show", "type", "unreachable"], timeout=20, check=False).stdout


@dataclass
class PlantLan:
    """One plant LAN stand-in and the Docker network ``zzz_layer2_net1`` over it."""

    tag: str  # one lower-case letter: several LANs of one run (one at a time: the name is global)
    label: str  # compose project label of the Docker network (found again if the run is killed)
    log_dir: Path
    processes: list[subprocess.Popen] = field(default_factory=list)
    created: list[str] = field(default_factory=list)

    @property
    def namespace(self) -> str:
        return f"lcl2-{os.getpid()}-{self.tag}"

    @property
    def parent(self) -> str:
        return f"l2h{os.getpid()}{self.tag}"

    def create(self, robot_address: str = "10.232.0.10") -> "PlantLan":
        existing = run(["docker", "network", "ls", "-q", "--filter", f"name=^{NETWORK}$"], timeout=30).stdout.strip()
        if existing:
            owner = run(["docker", "network", "inspect", "-f", '{{index .Labels "com.docker.compose.project"}}',
                         NETWORK], timeout=30, check=False).stdout.strip()
            raise DeployError(f"the Docker network {NETWORK} exists already (label {owner or 'none'}): one plant "
                              "LAN at a time (the name is the device's, global on the engine)")
        self.log_dir.mkdir(parents=True, exist_ok=True)
        peer = f"l2p{os.getpid()}{self.tag}"
        steps = [
            ["ip", "netns", "add", self.namespace],
            ["ip", "link", "add", self.parent, "type", "veth", "peer", "name", peer],
            ["ip", "link", "set", peer, "netns", self.namespace],
            ["ip", "-n", self.namespace, "link", "set", peer, "name", "eth0"],
            ["ip", "-n", self.namespace, "addr", "add", f"{robot_address}/24", "dev", "eth0"],
            ["ip", "-n", self.namespace, "link", "set", "lo", "up"],
            ["ip", "-n", self.namespace, "link", "set", "eth0", "up"],
        ]
        self.created.append("namespace")
        for argv in steps:
            run(argv, timeout=20)
        if not _route_present():
            run(["ip", "route", "add", "unreachable", SUBNET], timeout=20)
            self.created.append("route")
        # The parent: up (a macvlan over a link that is down carries nothing), no address, no
        # IPv6 (it would send router solicitations into the LAN), enslaved to nothing.
        Path(f"/proc/sys/net/ipv6/conf/{self.parent}/disable_ipv6").write_text("1\n")
        run(["ip", "netns", "exec", self.namespace, "sysctl", "-qw", "net.ipv6.conf.all.disable_ipv6=1"], timeout=20)
        run(["ip", "link", "set", self.parent, "up"], timeout=20)
        run(["docker", "network", "create", "--driver", "macvlan", "--subnet", SUBNET, "--ip-range", IP_RANGE,
             "--gateway", ROUTER, "--opt", f"parent={self.parent}", "--label",
             f"com.docker.compose.project={self.label}", NETWORK], timeout=60)
        self.created.append("network")
        return self

    def start(self, name: str, argv: list[str], env: dict[str, str]) -> subprocess.Popen:
        """A process inside the plant LAN (its output in ``log_dir/name.log``)."""
        log = open(self.log_dir / f"{name}.log", "ab")
        try:
            process = subprocess.Popen(
                ["ip", "netns", "exec", self.namespace, *argv], stdout=log, stderr=subprocess.STDOUT,
                env=env, cwd=ROOT, start_new_session=True,
            )
        finally:
            log.close()
        self.processes.append(process)
        return process

    def robot(self, name: str, domain: int, nodes: str = "lidar_driver,camera_driver") -> subprocess.Popen:
        """A simulated robot of this venv, with SUBNET discovery, as on any host of the LAN."""
        env = {k: v for k, v in os.environ.items() if not k.startswith(("ROS_", "RMW_", "FASTRTPS_", "FASTDDS_"))}
        env.update(ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET", PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
        process = self.start(name, [sys.executable, "-m", "ros_gateway.demo.robot", "--domain", str(domain),
                                    "--nodes", nodes], env)
        log = self.log_dir / f"{name}.log"

        def ready() -> bool:
            if process.poll() is not None:
                raise DeployError(f"robot {name} exited with {process.returncode}:\n{log.read_text(errors='replace')}")
            return "demo robot ready" in log.read_text(errors="replace")

        wait_for(ready, 60, f"robot {name} in {self.namespace}")
        return process

    def link_info(self) -> dict:
        """The parent link as the kernel has it: state, addresses, master."""
        addresses = run(["ip", "-o", "addr", "show", "dev", self.parent], timeout=20).stdout
        details = run(["ip", "-d", "-o", "link", "show", "dev", self.parent], timeout=20).stdout
        return {
            "up": ",UP" in details or "<UP" in details,
            "ipv4": re.findall(r"inet (\S+)", addresses),
            "master": re.search(r" master (\S+)", details) is not None,
            "veth": " veth " in f" {details} ",
        }

    def close(self) -> None:
        for process in self.processes:
            if process.poll() is None:
                try:
                    os.killpg(process.pid, signal.SIGTERM)
                    process.wait(10)
                except (ProcessLookupError, subprocess.TimeoutExpired):
                    try:
                        os.killpg(process.pid, signal.SIGKILL)
                    except ProcessLookupError:
                        pass
                    process.wait(5)
        if "network" in self.created:
            # Only ours (label): a network of that name made by someone else is never removed.
            names = run(["docker", "network", "ls", "-q", "--filter", f"name=^{NETWORK}$", "--filter",
                         f"label=com.docker.compose.project={self.label}"], timeout=30, check=False).stdout.split()
            if names:
                run(["docker", "network", "rm", *names], timeout=60, check=False)
        if "namespace" in self.created:
            _kill_inside(self.namespace)
            run(["ip", "netns", "delete", self.namespace], timeout=20, check=False)
            if self.parent in root_links():  # deleting the namespace takes the veth pair with it
                run(["ip", "link", "delete", self.parent], timeout=20, check=False)
        if "route" in self.created:
            _route("del")

    def leftovers(self) -> list[str]:
        left = [f"namespace {self.namespace}"] if self.namespace in namespaces() else []
        left += [f"link {self.parent}"] if self.parent in root_links() else []
        names = run(["docker", "network", "ls", "-q", "--filter", f"label=com.docker.compose.project={self.label}"],
                    timeout=30, check=False).stdout.split()
        left += [f"network {name}" for name in names]
        left += [f"process {p.pid}" for p in self.processes if p.poll() is None]
        left += [f"route unreachable {SUBNET}"] if "route" in self.created and _route_present() else []
        return left


def machine_interfaces(exclude: set[str]) -> list[str]:
    """Interfaces of the root namespace that lead off this machine or belong to others: all
    but loopback, the links given, and Docker's own bridges and veths (inside this machine)."""
    return [name for name in root_links()
            if name != "lo" and name not in exclude and name != "docker0" and not name.startswith(("br-", "veth"))]


def sniff(seconds: float, domains: list[int]) -> dict[str, list[tuple[str, str, int]]]:
    """IPv4 packets seen on any interface of the root namespace for ``seconds``, that belong to
    the plant LAN (from or to an address of SUBNET, NAT or not) or are DDS discovery multicast
    of ``domains`` (to 239.255.0.1 on the domain's discovery port; other ports of a domain's
    range are also unicast ports of other domains' participants on this busy machine):
    {interface: [(source, destination, destination port)]}. AF_PACKET, so as root only."""
    ports = {dds_ports(d)[0] for d in domains}
    group = socket.inet_aton(DDS_MULTICAST)
    prefix = socket.inet_aton(SUBNET.split("/")[0])[:3]
    seen: dict[str, list[tuple[str, str, int]]] = {}
    with socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.ntohs(0x0003)) as sock:
        sock.settimeout(0.2)
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            try:
                frame, address = sock.recvfrom(65535)
            except socket.timeout:
                continue
            if len(frame) < 38 or frame[12:14] != b"\x08\x00":
                continue
            header = (frame[14] & 0x0F) * 4
            source, destination = frame[26:30], frame[30:34]
            port = struct.unpack("!H", frame[16 + header:18 + header])[0] if frame[23] == 17 else 0
            if source[:3] == prefix or destination[:3] == prefix or (destination == group and port in ports):
                seen.setdefault(address[0], []).append((socket.inet_ntoa(source), socket.inet_ntoa(destination), port))
    return seen
