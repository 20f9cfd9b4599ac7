"""CPU and memory of a robot's processes, measured when someone asks (the Processes page, every few
seconds while it is open), never at rest: a launch profile's process with everything in its
process group (a launch file's nodes are its children), a container's or unit's every process in
its cgroup. One pass over /proc gives each process's group, CPU time and resident memory; CPU is
the share of one core since the previous ask (or over MEASURE_S on the first)."""
from __future__ import annotations

import asyncio
import os
import time
from pathlib import Path

from ros_gateway.host_units import cgroup_path
from ros_gateway.processes import stat_fields

MEASURE_S = 0.3  # the first ask (nothing to compare with) measures over this long
FORGET_S = 60.0  # a sample older than this is not compared with (a page opened much later)
TICKS = os.sysconf("SC_CLK_TCK")
PAGE = os.sysconf("SC_PAGE_SIZE")


def _scan(proc: Path, cgroups: bool) -> list[tuple[int, int, float, int, str]]:
    """(pid, process group, CPU seconds, resident bytes, cgroup or "") of every process."""
    found = []
    for name in os.listdir(proc):
        if not name.isdigit():
            continue
        fields = stat_fields(proc, int(name))  # after the name: state, ppid, pgrp, ... utime, stime, ... rss
        try:
            group = cgroup_path((proc / name / "cgroup").read_text()) if cgroups else ""
        except OSError:
            continue
        if fields is not None:
            found.append((int(name), int(fields[2]), (int(fields[11]) + int(fields[12])) / TICKS,
                          int(fields[21]) * PAGE, group))
    return found


class ProcessUsage:
    def __init__(self, proc: Path = Path("/proc")) -> None:
        self.proc = proc
        self._last: dict[str, tuple[float, float]] = {}  # process name -> (CPU seconds, monotonic)

    def _totals(self, groups: dict[str, int], cgroups: dict[str, set[str]]) -> dict[str, tuple[float, int, int]]:
        """name -> (CPU seconds, resident bytes, processes), for process groups and cgroups."""
        totals: dict[str, list] = {name: [0.0, 0, 0] for name in [*groups, *cgroups]}
        by_group = {pgid: name for name, pgid in groups.items()}
        by_cgroup = {path: name for name, paths in cgroups.items() for path in paths}
        for _pid, pgid, cpu, rss, group in _scan(self.proc, bool(cgroups)):
            name = by_group.get(pgid) or by_cgroup.get(group)
            if name is not None:
                total = totals[name]
                total[0] += cpu
                total[1] += rss
                total[2] += 1
        return {name: (cpu, rss, count) for name, (cpu, rss, count) in totals.items()}

    async def measure(self, groups: dict[str, int], cgroups: dict[str, set[str]]) -> dict[str, dict]:
        """``groups``: process name -> its process group; ``cgroups``: name -> its cgroup paths.
        name -> {"cpu_percent", "rss_bytes", "processes"} (cpu_percent None if not known)."""
        totals = await asyncio.to_thread(self._totals, groups, cgroups)  # (a pass over /proc: off the loop)
        now = time.monotonic()
        # Nothing to compare with: not asked about before, long ago, or since restarted (less CPU time).
        if any(name not in self._last or now - self._last[name][1] > FORGET_S or cpu < self._last[name][0]
               for name, (cpu, _, _) in totals.items()):
            self._last.update({name: (cpu, now) for name, (cpu, _, _) in totals.items()})
            await asyncio.sleep(MEASURE_S)
            totals = await asyncio.to_thread(self._totals, groups, cgroups)
            now = time.monotonic()
        usage = {}
        for name, (cpu, rss, count) in totals.items():
            before, at = self._last.get(name, (cpu, now))
            share = 100 * (cpu - before) / (now - at) if now - at > 0.05 and cpu >= before else None
            usage[name] = {"cpu_percent": None if share is None else round(share, 1), "rss_bytes": rss,
                           "processes": count}
            self._last[name] = (cpu, now)
        if len(self._last) > 4 * max(len(totals), 64):  # processes gone since
            self._last = {name: v for name, v in self._last.items() if now - v[1] <= FORGET_S}
        return usage
