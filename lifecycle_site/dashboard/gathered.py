"""A live page's part drawn once for a burst of updates (a mode applied to 50 nodes, a robot's
statuses changing together): the first update waits a moment for the others, and updates that come
while one is being drawn make one more drawing, not one each."""
from __future__ import annotations

import asyncio


class GatheredDraws:
    """Mixed into a consumer that has ``async def draw()``. A drawing that waits longer than a new
    update asks for (a freshness-only update waits a second, a level change milliseconds) is
    brought forward."""

    pending: asyncio.Task | None = None
    due_at = 0.0  # (the loop's clock) when the pending drawing begins
    drawing = False
    again = False

    async def draw(self) -> None:
        raise NotImplementedError

    def soon(self, wait: float) -> None:
        due = asyncio.get_running_loop().time() + wait
        if self.pending is not None and not self.pending.done():
            if self.drawing or due >= self.due_at:
                self.again = True
                return
            self.pending.cancel()  # still waiting, for longer than this update may
        self.due_at = due
        self.pending = asyncio.ensure_future(self._gathered(wait))

    async def _gathered(self, wait: float) -> None:
        await asyncio.sleep(wait)
        self.drawing = True
        try:
            await self.draw()
            while self.again:
                self.again = False
                await self.draw()
        finally:
            self.drawing = False

    def stop_drawing(self) -> None:
        if self.pending is not None:
            self.pending.cancel()
