"""Claims on ROS domain ids, so two test or benchmark runs on one machine never share one.

Two runs in one domain see each other's nodes under the same names: a service request then
reaches both processes and the first answer wins, which looks like a node that changed state
or restarted on its own. A claim is an exclusive ``flock`` on a file per domain id, held
until the process exits (the kernel drops it even after a crash).
"""
from __future__ import annotations

import atexit
import fcntl
import os
import random
import tempfile
from typing import IO

_held: dict[int, IO] = {}


class DomainInUse(RuntimeError):
    """Another run on this machine holds the domain."""


def _path(domain_id: int) -> str:
    return os.path.join(tempfile.gettempdir(), f"lifecycle-ros-domain-{domain_id}.lock")


def claim(domain_ids: list[int]) -> None:
    """Claim all the domains or none; DomainInUse names the first one taken."""
    taken: list[int] = []
    try:
        for domain_id in domain_ids:
            if domain_id in _held:
                continue
            handle = open(_path(domain_id), "w")
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                handle.close()
                raise DomainInUse(f"ROS domain {domain_id} is in use by another run on this machine") from None
            _held[domain_id] = handle
            taken.append(domain_id)
    except DomainInUse:
        release(taken)
        raise


def release(domain_ids: list[int]) -> None:
    for domain_id in domain_ids:
        handle = _held.pop(domain_id, None)
        if handle is not None:
            handle.close()


@atexit.register
def _release_all() -> None:
    release(list(_held))


def claim_block(size: int, *ranges: tuple[int, int]) -> int:
    """Claim ``size`` consecutive domains in one of the slots low, low + size, ... of the ranges
    (each ending by its high); returns the base. The first range's slots are tried first, each
    range's in random order. Slots, not any base: one run at a random base could otherwise leave
    no room for a second one."""
    bases: list[int] = []
    for low, high in ranges:
        slots = list(range(low, high - size + 1, size))
        random.shuffle(slots)
        bases += slots
    for base in bases:
        try:
            claim(list(range(base, base + size)))
        except DomainInUse:
            continue
        return base
    spans = ", ".join(f"{low}-{high - 1}" for low, high in ranges)
    raise DomainInUse(f"all {len(bases)} blocks of {size} ROS domains in {spans} are in use by other test runs "
                      "on this machine")
