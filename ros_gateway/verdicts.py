"""Whether the site has ended a run this gateway is still carrying out.

The site ends a run on its own when the gateway has been silent too long (frozen, cut off,
killed), and says so under the gateway's keys (``protocol.verdict_key``). A verdict is final:
before a run's next step, if more than CHECK_AFTER_S passed since the site was last asked
(any pause: the process stopped, Redis away, a slow step), the gateway asks again, one GET,
and stops the run if the site has ended it. If it cannot ask, it stops too: better a run
stopped than a node driven for a run that may be over.
"""
from __future__ import annotations

import asyncio
import json
import logging
import time

from ros_gateway.relay import Relay

log = logging.getLogger(__name__)

# Steps closer together than this go on without asking (a run of quick steps costs no round trips).
CHECK_AFTER_S = 1.0
# How long one question may take; a Redis that does not answer by then counts as unreachable.
ANSWER_WITHIN_S = 3.0
# A question whose answer took longer than CHECK_AFTER_S (the process stopped meanwhile) is asked
# again, this many times in all, before the run stops for want of a fresh answer.
ASKS = 3


class RunVerdict:
    """One run's view of the site's verdict; ``ended`` says why the run must not go on."""

    def __init__(self, relay: Relay, run_id: str) -> None:
        self.relay, self.run_id = relay, run_id
        self.asked = time.monotonic()  # the run was handed over just now
        self.ended: str = ""
        self.status = ""  # the site's status for the run, when it has ended it
        self._asking = asyncio.Lock()  # the nodes of a tier share one question

    async def may_step(self) -> bool:
        """Whether the run may take its next step (asks the site first after a pause)."""
        async with self._asking:
            for _ in range(ASKS):
                if self.ended or time.monotonic() - self.asked <= CHECK_AFTER_S:
                    return not self.ended
                await self._ask()
            if not self.ended:
                self._end("", f"the gateway could not get a timely answer from Redis (within {CHECK_AFTER_S:g} s) "
                          "on whether the site had ended the run")
            return False

    async def _ask(self) -> None:
        sent = time.monotonic()
        try:
            async with asyncio.timeout(ANSWER_WITHIN_S):
                raw = await self.relay.read_verdict(self.run_id)
        except Exception as exc:  # Redis away, no answer, no permission: nobody can say the run goes on
            self._end("", f"the gateway could not ask Redis whether the site had ended the run "
                      f"({type(exc).__name__}: {str(exc) or f'no answer within {ANSWER_WITHIN_S:g} s'})")
            return
        if raw is None:
            self.asked = sent
            return
        try:
            verdict = json.loads(raw)
        except ValueError:
            verdict = {}
        if not isinstance(verdict, dict):
            verdict = {}
        status = str(verdict.get("status") or "failed")
        self._end(status, f"the site had already ended the run as {status}",
                  f" at {verdict.get('at')}: {verdict.get('message')}")

    def _end(self, status: str, reason: str, detail: str = "") -> None:
        self.ended, self.status = reason, status
        log.warning("run %s stops, no further node is driven: %s%s", self.run_id, reason, detail)
