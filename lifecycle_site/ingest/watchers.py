"""Who watches what the ingest process stores. Other apps register here (the alert rules:
alerts/apps.py), so that fleet, which stores the facts, imports none of them.

The ingest process that leads (shares.py) starts one of each registered watcher, hands it
every observation of the site, calls ``tick`` about once per loop and ``stop`` at its end."""
from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

from lifecycle_site.ingest.observations import Observation


class Watcher(Protocol):
    def take(self, seen: list[Observation]) -> None:
        """Observations just stored (cheap: the work is done in ``tick``)."""

    def tick(self) -> None:
        """One turn; raises only what the ingest loop retries (the database unavailable)."""

    def stop(self) -> None: ...


_factories: list[Callable[[], Watcher]] = []


def register(factory: Callable[[], Watcher]) -> None:
    if factory not in _factories:
        _factories.append(factory)


def start() -> list[Watcher]:
    return [factory() for factory in _factories]
