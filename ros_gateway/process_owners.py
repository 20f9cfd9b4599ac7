"""Which launch profile's process each node runs in (so the site can offer "restart process" on
the node's page): the node's DDS participant is a process of this host (processes.LocalProcesses
matches it by its GUID), and that process, or one of its ancestors (``ros2 launch`` starts the
nodes as its children), is one the supervisor started. Nodes of other hosts, or of processes
this gateway does not run, have none.

A node of no launch profile whose process is in a Docker container or a systemd unit of this host
is that unit's (host_units.py: "docker:NAME", "systemd:UNIT"), where its supervisor is reachable."""
from __future__ import annotations

from pathlib import Path
from typing import Callable

from ros_gateway.host_units import HostUnits
from ros_gateway.processes import LocalProcesses, parent_pid
from ros_gateway.registry import LiveNode, NodeRegistry

MAX_DEPTH = 16  # ancestors looked at (a launch file's nodes are its children or grandchildren)


class ProcessOwners:
    def __init__(self, registry: NodeRegistry, processes: LocalProcesses, supervised: Callable[[], dict],
                 report: Callable[[LiveNode], None], units: HostUnits | None = None,
                 proc: Path = Path("/proc")) -> None:
        """``supervised()``: pid -> (robot, profile name) of the running supervised processes;
        ``report(node)``: called when a node's owner (``node.process``) changed; ``units``: the
        host's containers and systemd units (None: not looked at)."""
        self.registry, self.processes, self.supervised, self.report, self.units, self.proc = (
            registry, processes, supervised, report, units, proc)
        self._looked: dict[str, tuple] = {}  # node key -> (its participants, the supervised pids) looked at

    async def refresh(self) -> None:
        owners = self.supervised()
        pids = frozenset(owners)
        for node in list(self.registry.nodes.values()):
            if not node.alive or self._looked.get(node.key) == (node.live, pids):
                continue
            owner = self.owner(node, owners)
            settled = bool(owner)
            if not owner:
                owner, settled = await self._unit(node)
            if settled:  # else looked at again next time (a process not matched yet, a supervisor not answering)
                self._looked[node.key] = (node.live, pids)
            if not owner and node.process and not self._runs(node):
                continue  # its process has ended (its node not marked gone yet): it keeps its owner
            if owner != node.process:
                node.process = owner
                self.report(node)
        if len(self._looked) > 4 * max(1, len(self.registry.nodes)):  # nodes forgotten since
            self._looked = {k: v for k, v in self._looked.items() if k in self.registry.nodes}

    def _runs(self, node: LiveNode) -> bool:
        """Whether a process of this host that runs the node is known and running."""
        domain = node.robot.domain_id
        return any(self.processes.process(domain, p) is not None and not self.processes.ended(domain, p)
                   for p in node.live)

    async def _unit(self, node: LiveNode) -> tuple[str, bool]:
        """The container or unit running the node's process ("" if none is known), attributed to
        its robot; and whether that is settled (False: a process of this host not matched yet, or
        a unit whose supervisor did not tell its name)."""
        domain = node.robot.domain_id
        settled = True
        for prefix in node.live:
            found = self.processes.process(domain, prefix)
            if found is None:
                settled = settled and not self.processes.unmatched(domain, prefix)
                continue
            if self.units is None:
                continue
            unit = await self.units.identify(found.pid)
            if unit is not None:
                self.units.attribute(node.robot.name, unit)
                return unit.name, True
            settled = settled and self.units.identified(found.pid)
        return "", settled

    def owner(self, node: LiveNode, owners: dict[int, tuple[str, str]]) -> str:
        """The launch profile whose process (or a descendant of it) runs the node, or ""."""
        for prefix in node.live:
            found = self.processes.process(node.robot.domain_id, prefix)
            pid = found.pid if found is not None else None
            for _ in range(MAX_DEPTH):
                if pid is None or pid <= 1:
                    break
                if pid in owners:
                    robot, name = owners[pid]
                    return name if robot == node.robot.name else ""
                pid = parent_pid(self.proc, pid)
        return ""
