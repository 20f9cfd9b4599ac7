"""A live page's part drawn once for a burst of updates (a mode applied to 50 nodes, a robot's
statuses changing together): the first update waits a moment for the others, and updates that come
while one is being drawn make one more drawing, not one each."""
from __future__ import annotations

import asyncio


class GatheredDraws:
    """Mixed into a consumer that has ``async def draw()``."""

    pending: asyncio.Task | None = None
    again = False

    async def draw(self) -> None:
        raise NotImplementedError

    def soon(self, wait: float) -> None:
        if self.pending is None or self.pending.done():
            self.pending = asyncio.ensure_future(self._gathered(wait))
        else:
            self.again = True

    async def _gathered(self, wait: float) -> None:
        await asyncio.sleep(wait)
        await self.draw()
        while self.again:
            self.again = False
            await self.draw()

    def stop_drawing(self) -> None:
        if self.pending is not None:
            self.pending.cancel()
