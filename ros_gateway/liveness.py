"""Whether the processes behind the watched nodes still answer.

A robot host whose link goes down keeps its nodes in the DDS graph until their participant's
lease runs out (about 20 s with Fast DDS's defaults, 24 s measured), and the lease is the
robot's setting, not ours. So the gateway asks: every ``interval`` one ``get_state`` per
robot *process* (a DDS participant, known from the first 12 bytes of its endpoints' ids),
not per node. A process that misses ``misses`` probes in a row (each bounded by ``timeout``)
is unreachable: its nodes go (``node.gone``, reason "unreachable") and discovery holds them
back until a probe is answered again. At 1,000 nodes in 20 processes that is 20 small
service calls per interval.

A process new to the graph whose nodes' states have not been read yet is left alone for
NEW_PROCESS_GRACE_S: DDS matches a new process's services both ways only after a moment (seconds
on a busy host; requests meanwhile go unanswered), and discovery is reading its states anyway.
A node restarted under the same name would otherwise flash "unreachable" just after it came back.

A process of the gateway's own host whose pid is known (processes.py) cannot lose its link,
and its end is seen in /proc at once: its probes only find a hang (a callback that never
returns), and come every LOCAL_EVERY passes. With 20 such processes at rest the probes were
most of the gateway's CPU (0.9 of 2.3 % of a core). One that /proc shows stopped (SIGSTOP, a
debugger) is probed at every pass, as a remote one: found within interval + misses x timeout.

A process busy in a transition (a node of it in a transition state, or one our command is
driving) is not probed: a single-threaded robot cannot answer while its callback runs. Unless
discovery found a node of it stuck in that state and silent (``suspect``): killed in the middle
of a transition, its process would otherwise be seen gone only when its DDS lease runs out.
"""
from __future__ import annotations

import logging
import time
from collections import defaultdict
from typing import Callable

from ros_gateway.domain import RosDomain
from ros_gateway.lifecycle import NodeUnreachable, read_state
from ros_gateway.registry import GUID_PREFIX_BYTES, LiveNode, NodeRegistry
from ros_gateway.shared import state_machine as sm
from ros_gateway.tasks import spawn

log = logging.getLogger(__name__)

UNREACHABLE = "unreachable"
NEW_PROCESS_GRACE_S = 5.0
LOCAL_EVERY = 3  # passes between two probes of a process of this host (see above)

# (domain id, participant) -- or (domain id, node name) while a node's endpoints are unknown.
Process = tuple[int, bytes | str]


def participants(node_name: str, incarnation: frozenset) -> set[bytes | str]:
    """The DDS participants publishing the node's transition events (the node's name while
    none is known)."""
    return {bytes(gid)[:GUID_PREFIX_BYTES] for gid in incarnation} or {node_name}


def process_of(domain_id: int, node_name: str, incarnation: frozenset) -> Process:
    """The one process a node is probed with (the first of its participants)."""
    return domain_id, min(participants(node_name, incarnation))  # all bytes, or the one name


def process_now(node: LiveNode) -> Process:
    """The process a node is probed with now: the one it is believed to run in."""
    return process_of(node.robot.domain_id, node.name, node.live or node.incarnation)


class Liveness:
    def __init__(self, registry: NodeRegistry, domains: dict[int, RosDomain], interval: float, timeout: float,
                 misses: int = 2, local: Callable[[int, bytes], bool] | None = None) -> None:
        """``local(domain id, participant)``: whether that participant is a process of this host
        (None: none is known to be)."""
        self.registry, self.domains, self.local = registry, domains, local
        self.interval, self.timeout, self.misses = interval, timeout, misses
        self.unreachable: dict[Process, float] = {}  # process -> since (monotonic)
        self._probing: set[Process] = set()
        self._suspects: set[Process] = set()  # probed although busy: stuck in a transition, silent
        self._first_seen: dict[Process, float] = {}  # process -> when a probe pass first found it (monotonic)
        self.probes = 0  # service calls made, for the gateway's statistics
        self._passes = 0

    @property
    def enabled(self) -> bool:
        return self.interval > 0

    def holds_back(self, domain: RosDomain, node_name: str, departed: frozenset = frozenset()) -> bool:
        """Whether discovery should not (yet) call this node alive: its process does not answer.
        A node restarted under the same name lists its old and new endpoints for a while; it
        is held back only if none of them belongs to a process that may answer (``departed``:
        processes known to have ended, left out)."""
        if not self.unreachable:
            return False
        alive = participants(node_name, domain.incarnation(node_name)) - departed
        return bool(alive) and all((domain.domain_id, participant) in self.unreachable for participant in alive)

    def suspect(self, node: LiveNode) -> None:
        """Probe the node's process even though the node sits in a transition state."""
        self._suspects.add(process_now(node))

    def _groups(self) -> dict[Process, list[LiveNode]]:
        """Watched nodes by process: the live ones, and those of unreachable processes."""
        groups: dict[Process, list[LiveNode]] = defaultdict(list)
        for (domain_id, name), node in self.registry.nodes.items():
            process = process_of(domain_id, name, node.live or node.incarnation)
            if node.alive or process in self.unreachable:
                groups[process].append(node)
        return groups

    async def probe(self) -> None:
        """One pass: start a probe of every process not being probed already."""
        groups = self._groups()
        for process in list(self.unreachable):
            if process not in groups:  # its nodes left the graph or our robots for good
                del self.unreachable[process]
        self._suspects &= set(groups)
        now = time.monotonic()
        self._first_seen = {process: self._first_seen.get(process, now) for process in groups}
        self._passes += 1
        for process, nodes in groups.items():
            if process in self._probing or process[0] not in self.domains or any(n.lock.locked() for n in nodes):
                continue
            if self._passes % LOCAL_EVERY and self._local(process):
                continue  # of this host: a hang is all a probe can find there (see the module's docstring)
            if now - self._first_seen[process] < NEW_PROCESS_GRACE_S and not any(n.state_read for n in nodes):
                continue  # new, and not heard from yet (see the module's docstring)
            if process not in self._suspects and any(n.alive and not sm.is_primary(n.state_id) for n in nodes):
                continue  # busy in a transition: it may not answer until that is over
            self._probing.add(process)
            spawn(self._probe(process, nodes))

    def _local(self, process: Process) -> bool:
        """Whether the process is one of this host, and neither unreachable nor a suspect."""
        domain_id, participant = process
        return (self.local is not None and isinstance(participant, bytes) and process not in self.unreachable
                and process not in self._suspects and self.local(domain_id, participant))

    async def _probe(self, process: Process, nodes: list[LiveNode]) -> None:
        domain = self.domains[process[0]]
        try:
            for attempt in range(self.misses):
                node = nodes[attempt % len(nodes)]
                self.probes += 1
                try:
                    await read_state(domain, node.name, self.timeout)
                except NodeUnreachable:
                    continue
                self._suspects.discard(process)
                if self.unreachable.pop(process, None) is not None:
                    log.info("the process of %s on %s answers again", node.name, node.robot.name)
                return
            # A node may have come back in a new process while its old one was probed (a
            # restart under the same name): only those still in the silent process are lost.
            still = [n for n in nodes if n.alive and process_now(n) == process]
            if process not in self.unreachable and still:
                self._lost(process, still)
        finally:
            self._probing.discard(process)

    def _lost(self, process: Process, nodes: list[LiveNode]) -> None:
        self._suspects.discard(process)
        self.unreachable[process] = time.monotonic()
        missed = f"{self.misses} probe{'s' if self.misses > 1 else ''} of {self.timeout:g} s"
        log.warning("no answer from the process of %s on %s (%s): its %d node(s) are unreachable",
                    nodes[0].name, nodes[0].robot.name, missed, len(nodes))
        for node in nodes:
            if node.alive:
                self.registry.vanished(node, reason=UNREACHABLE)
