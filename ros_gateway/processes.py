"""Whether the process behind a node has ended, and the audit facts saying a process was lost
or replaced by a new instance.

DDS alone learns late that a process crashed: its nodes stay in the graph until the
participant's lease runs out (about 20 s with Fast DDS's defaults, measured 19.7 s after a
kill -9). On the gateway's own host it need not wait. A Fast DDS participant's GUID prefix
carries its vendor (01 0f), its host id (bytes 2-3) and the low 16 bits of its process id
(bytes 4-5): a participant of this host is matched once to the one process with those low
bits that maps Fast DDS's shared-memory ports of the participant's ROS domain, and from then on
a missing ``/proc`` entry, a zombie or another start time means it ended, at once. (A process in a
container with the host's network has the host's id; its GUID has the pid it sees in its own PID
namespace, which ``/proc/PID/status``'s NSpid tells.) Anywhere
else the signs are the node leaving the graph and a new process publishing its
``~/transition_event`` (a restart).
"""
from __future__ import annotations

import logging
import os
import re
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Iterable

from ros_gateway.outbox import Outbox
from ros_gateway.registry import LiveNode, StateChange
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm

log = logging.getLogger(__name__)

FASTDDS_VENDOR = b"\x01\x0f"
PROCESS_LOST, PROCESS_RESTARTED = protocol.PROCESS_LOST, protocol.PROCESS_RESTARTED
# Matched processes remembered at most (participants of nodes that come and go).
KNOWN_LIMIT = 4096
# RTPS well-known ports: a domain's participants use ports PB + DG * domain ... below the next
# domain's; Fast DDS's shared-memory transport names its port segments after them.
PORT_BASE, DOMAIN_GAIN = 7400, 250
SHM_PORT = re.compile(r"/dev/shm/fastrtps_port(\d+)")
# A participant of this host not matched to one process (not there yet, or ambiguous) is looked
# for again after RETRY_FIRST_S, then after twice as long each time, up to RETRY_MAX_S.
RETRY_FIRST_S, RETRY_MAX_S = 1.0, 60.0


@dataclass(frozen=True)
class OsProcess:
    pid: int
    started: str  # /proc/PID/stat start time (clock ticks since boot): tells a reused PID apart


def stat_fields(proc: Path, pid: int) -> list[str] | None:
    """/proc/PID/stat's fields after the name (state, ppid, ...), or None if there is no such process."""
    try:
        text = (proc / str(pid) / "stat").read_text()
    except OSError:
        return None
    return text[text.rindex(")") + 2:].split()  # the name in parentheses may hold spaces


def _stat(proc: Path, pid: int) -> tuple[str, str] | None:
    """(state letter, start time) of a process, or None if there is none."""
    fields = stat_fields(proc, pid)
    return None if fields is None else (fields[0], fields[19])


def parent_pid(proc: Path, pid: int) -> int | None:
    """The process's parent, or None if there is no such process."""
    fields = stat_fields(proc, pid)
    return int(fields[1]) if fields and len(fields) > 1 and fields[1].isdigit() else None


def _inner_pid(proc: Path, pid: int) -> int:
    """The pid the process sees in its own PID namespace (a container's), or -1 if it is in ours."""
    try:
        with open(proc / str(pid) / "status") as status:
            for line in status:
                if line.startswith("NSpid:"):
                    ids = line.split()[1:]
                    return int(ids[-1]) if len(ids) > 1 else -1
    except (OSError, ValueError):
        pass
    return -1


def _maps_domain_ports(proc: Path, pid: int, domain_id: int) -> bool:
    """Whether the process maps a Fast DDS shared-memory port of the ROS domain."""
    try:
        maps = (proc / str(pid) / "maps").read_text()
    except OSError:  # gone, or not ours to read
        return False
    low = PORT_BASE + DOMAIN_GAIN * domain_id
    return any(low <= int(port) < low + DOMAIN_GAIN for port in SHM_PORT.findall(maps))


class LocalProcesses:
    """The OS processes of this host's Fast DDS participants, found once and then watched."""

    def __init__(self, proc: Path = Path("/proc")) -> None:
        self.proc = proc
        self.host: bytes | None = None  # our own participants' host id (set by the first domain)
        # (domain id, participant) -> its process, once matched
        self._known: dict[tuple[int, bytes], OsProcess] = {}
        # (domain id, participant of this host) -> (when to look again, the last wait) while not matched
        self._retry: dict[tuple[int, bytes], tuple[float, float]] = {}

    def learn_host(self, own_gid: bytes | None) -> None:
        if own_gid and self.host is None and bytes(own_gid)[:2] == FASTDDS_VENDOR:
            self.host = bytes(own_gid)[2:4]

    def ours(self, prefix: bytes) -> bool:
        """Whether the participant is of this host (False while that is not known yet)."""
        return self.host is not None and prefix[:2] == FASTDDS_VENDOR and prefix[2:4] == self.host

    def unmatched(self, domain_id: int, prefix: bytes) -> bool:
        """Whether the participant may be a process of this host not matched yet (looked for again later)."""
        return self.host is None or (self.ours(prefix) and (domain_id, prefix) not in self._known)

    def stopped(self, process: OsProcess) -> bool:
        """Whether the process is stopped (SIGSTOP, a debugger's hold): it answers nothing."""
        fields = stat_fields(self.proc, process.pid)
        return fields is not None and fields[0] in ("T", "t")

    def _match(self, domain_id: int, prefix: bytes) -> OsProcess | None:
        low = int.from_bytes(prefix[4:6], "little")
        try:
            pids = [int(name) for name in os.listdir(self.proc) if name.isdigit()]
        except OSError:
            return None
        matches = [pid for pid in pids if pid & 0xFFFF == low and _maps_domain_ports(self.proc, pid, domain_id)]
        if not matches:  # a container's process (with the host's network: the same host id) knows its own pid
            matches = [pid for pid in pids if _inner_pid(self.proc, pid) & 0xFFFF == low
                       and _maps_domain_ports(self.proc, pid, domain_id)]
        if len(matches) != 1:  # none or ambiguous: rely on DDS
            return None
        stat = _stat(self.proc, matches[0])
        if stat is None or stat[0] in "ZX":
            return None
        return OsProcess(matches[0], stat[1])

    def process(self, domain_id: int, prefix: bytes) -> OsProcess | None:
        if self.host is None:
            return None  # not known yet which host is ours: look again later
        key = (domain_id, prefix)
        found = self._known.get(key)
        if found is not None or not self.ours(prefix):
            return found  # another vendor's or another host's participant: nothing to look up here
        now = time.monotonic()
        retry = self._retry.get(key)
        if retry is not None and now < retry[0]:
            return None
        # Not matched once is not for good: a process just started, or looked at while another
        # with the same low pid bits also mapped the domain's ports, is matched on a later look.
        found = self._match(domain_id, prefix)
        if found is None:
            if len(self._retry) >= KNOWN_LIMIT:
                self._retry.clear()
            wait = min(RETRY_MAX_S, retry[1] * 2) if retry else RETRY_FIRST_S
            self._retry[key] = (now + wait, wait)
            return None
        self._retry.pop(key, None)
        if len(self._known) >= KNOWN_LIMIT:
            self._known.clear()
        self._known[key] = found
        return found

    def ended(self, domain_id: int, prefix: bytes) -> bool:
        """Whether the participant is known to be of a process of this host that has ended."""
        found = self.process(domain_id, prefix)
        if found is None:
            return False
        stat = _stat(self.proc, found.pid)
        return stat is None or stat[0] in "ZX" or stat[1] != found.started

    def all_ended(self, domain_id: int, prefixes: frozenset, ended: set[bytes] | None = None) -> bool:
        """Whether every one of these participants is known to have ended (False for none);
        ``ended``: those found ended by ``ended_among`` just before (one look per process)."""
        if ended is not None:
            return bool(prefixes) and prefixes <= ended
        return bool(prefixes) and all(self.ended(domain_id, prefix) for prefix in prefixes)

    def ended_among(self, domain_id: int, prefixes: Iterable[bytes]) -> set[bytes]:
        """The participants among these that are known to have ended."""
        return {prefix for prefix in set(prefixes) if self.ended(domain_id, prefix)}


def lost_message(node: LiveNode, how: str) -> str:
    return (f"The process of {node.name} on {node.robot.name} {how}; its last known state was "
            f"{sm.state_label(node.state_id)}. A supervisor (launch respawn, systemd) may start it again: "
            "it then shows as a new instance, unconfigured.")


class ProcessRecords:
    """Audit facts of processes lost and restarted outside a transition of ours."""

    def __init__(self, outbox: Outbox) -> None:
        self.outbox = outbox

    def lost(self, node: LiveNode, how: str) -> dict:
        """Record that the node's process was lost (the node has been marked gone)."""
        at = node.process_since or datetime.now(timezone.utc)
        log.warning("the process of %s on %s %s", node.name, node.robot.name, how)
        return self._record(node, PROCESS_LOST, start=node.state_id, result=None, at=at,
                            message=lost_message(node, how))

    def on_change(self, change: StateChange) -> None:
        """State-change listener: the first state read from a new instance of a node's process."""
        if change.kind != "state" or not change.respawned:
            return
        node = change.node
        at = node.process_since or datetime.now(timezone.utc)
        message = (f"A new instance of {node.name}'s process is running on {node.robot.name} "
                   f"(new DDS endpoints under the same name); its state, read now, is "
                   f"{sm.state_label(change.state_id)} and its parameters are read again.")
        log.info("%s on %s: new process instance, %s", node.name, node.robot.name, sm.state_label(change.state_id))
        self._record(node, PROCESS_RESTARTED, start=None, result=change.state_id, at=at, message=message)

    def _record(self, node: LiveNode, outcome: str, *, start: int | None, result: int | None, at: datetime,
                message: str) -> dict:
        when = at.isoformat()
        return self.outbox.emit(
            protocol.TRANSITION, robot=node.robot.name, node=node.name, transition_id=None, transition_label="",
            start_state=start if start is not None and start != sm.UNKNOWN else None, result_state=result,
            outcome=outcome, source="external", user_id=None, requested_at=when, completed_at=when,
            error=message, run_id="",
        )
