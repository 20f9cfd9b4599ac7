"""A live page's drawings gathered (lifecycle_site/dashboard/gathered.py): a burst drawn once and
once more for what came meanwhile; an urgent update brings a slow pending drawing forward."""
from __future__ import annotations

import asyncio

from lifecycle_site.dashboard.gathered import GatheredDraws


class Page(GatheredDraws):
    def __init__(self) -> None:
        self.drawn: list[float] = []

    async def draw(self) -> None:
        self.drawn.append(asyncio.get_running_loop().time())
        await asyncio.sleep(0.02)


def test_a_burst_is_drawn_once_and_once_more_for_what_came_while_drawing():
    async def scenario() -> list[float]:
        page = Page()
        for _ in range(10):
            page.soon(0.01)
        await asyncio.sleep(0.02)  # drawing now
        page.soon(0.01)
        page.soon(0.01)
        await asyncio.sleep(0.1)
        return page.drawn

    assert len(asyncio.run(scenario())) == 2


def test_an_urgent_update_does_not_wait_for_a_quiet_one():
    async def scenario() -> tuple[float, list[float]]:
        page = Page()
        page.soon(1.0)  # freshness only: a second is fine
        await asyncio.sleep(0.05)
        began = asyncio.get_running_loop().time()
        page.soon(0.01)  # a level change
        await asyncio.sleep(0.1)
        page.stop_drawing()
        return began, page.drawn

    began, drawn = asyncio.run(scenario())
    assert len(drawn) == 1 and drawn[0] - began < 0.05
