"""Which launch profile's process each node runs in (so the site can offer "restart process" on
the node's page): the node's DDS participant is a process of this host (processes.LocalProcesses
matches it by its GUID), and that process, or one of its ancestors (``ros2 launch`` starts the
nodes as its children), is one the supervisor started. Nodes of other hosts, or of processes
this gateway does not run, have none."""
from __future__ import annotations

from pathlib import Path
from typing import Callable

from ros_gateway.processes import LocalProcesses, parent_pid
from ros_gateway.registry import LiveNode, NodeRegistry

MAX_DEPTH = 16  # ancestors looked at (a launch file's nodes are its children or grandchildren)


class ProcessOwners:
    def __init__(self, registry: NodeRegistry, processes: LocalProcesses, supervised: Callable[[], dict],
                 report: Callable[[LiveNode], None], proc: Path = Path("/proc")) -> None:
        """``supervised()``: pid -> (robot, profile name) of the running supervised processes;
        ``report(node)``: called when a node's owner (``node.process``) changed."""
        self.registry, self.processes, self.supervised, self.report, self.proc = (
            registry, processes, supervised, report, proc)
        self._looked: dict[str, tuple] = {}  # node key -> (its participants, the supervised pids) looked at

    def refresh(self) -> None:
        owners = self.supervised()
        pids = frozenset(owners)
        for node in list(self.registry.nodes.values()):
            if not node.alive or self._looked.get(node.key) == (node.live, pids):
                continue
            self._looked[node.key] = (node.live, pids)
            owner = self.owner(node, owners)
            if owner != node.process:
                node.process = owner
                self.report(node)
        if len(self._looked) > 4 * max(1, len(self.registry.nodes)):  # nodes forgotten since
            self._looked = {k: v for k, v in self._looked.items() if k in self.registry.nodes}

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
