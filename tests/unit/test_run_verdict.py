"""Before a run's next step after a pause, the gateway asks whether the site has ended the run
(ros_gateway/verdicts.py): steps close together cost no question, a verdict stops the run, and so
does a Redis that cannot be asked."""
from __future__ import annotations

import asyncio
import json

import pytest

from ros_gateway import verdicts
from ros_gateway.verdicts import RunVerdict


class Relay:
    """Answers read_verdict as told: a value, None, or an exception to raise."""

    def __init__(self, answer: object = None, delay: float = 0.0) -> None:
        self.answer, self.delay, self.asked = answer, delay, 0

    async def read_verdict(self, run_id: str) -> bytes | None:
        self.asked += 1
        await asyncio.sleep(self.delay)
        if isinstance(self.answer, Exception):
            raise self.answer
        return self.answer


@pytest.fixture(autouse=True)
def short_bounds(monkeypatch):
    monkeypatch.setattr(verdicts, "CHECK_AFTER_S", 0.05)
    monkeypatch.setattr(verdicts, "ANSWER_WITHIN_S", 0.2)


def steps(relay: Relay, pause: float, tier: int = 1) -> tuple[list[bool], RunVerdict]:
    """May the run step: at once, then after ``pause`` (``tier`` nodes asking together)."""
    verdict = RunVerdict(relay, "r1")

    async def main() -> list[bool]:
        first = await verdict.may_step()
        await asyncio.sleep(pause)
        return [first, *await asyncio.gather(*(verdict.may_step() for _ in range(tier)))]

    return asyncio.run(main()), verdict


def test_steps_close_together_go_on_without_asking():
    relay = Relay(answer=b'{"status": "failed"}')
    allowed, verdict = steps(relay, 0.0)
    assert allowed == [True, True] and relay.asked == 0 and not verdict.ended


def test_after_a_pause_the_site_is_asked_once_for_a_whole_tier_and_no_verdict_lets_it_go_on():
    relay = Relay(answer=None)
    allowed, _ = steps(relay, 0.1, tier=8)
    assert allowed == [True] * 9 and relay.asked == 1


def test_a_verdict_stops_the_run_with_the_sites_status():
    relay = Relay(answer=json.dumps({"status": "failed", "message": "silent", "at": "2026-01-01T00:00:00+00:00"}))
    allowed, verdict = steps(relay, 0.1, tier=3)
    assert allowed == [True, False, False, False] and relay.asked == 1
    assert (verdict.status, verdict.ended) == ("failed", "the site had already ended the run as failed")


def test_a_redis_that_cannot_be_asked_stops_the_run():
    for answer, delay in ((ConnectionError("Connection refused"), 0.0), (None, 1.0)):  # refused, no answer
        relay = Relay(answer=answer, delay=delay)
        allowed, verdict = steps(relay, 0.1)
        assert allowed == [True, False] and verdict.status == ""
        assert verdict.ended.startswith("the gateway could not ask Redis whether the site had ended the run"), \
            verdict.ended


def test_an_answer_that_comes_after_a_pause_is_asked_for_again():
    relay = Relay(answer=None, delay=0.1)  # each answer older than CHECK_AFTER_S when it comes
    allowed, verdict = steps(relay, 0.1)
    assert allowed == [True, False] and relay.asked == verdicts.ASKS
    assert "timely answer" in verdict.ended
