"""The pipeline harness waits for a backlog to drain after the replay (``harness._drain``)."""

from __future__ import annotations

import asyncio
import time

from labeler_service.testing import harness


def _timed(count, expected, frames_later=()):
    async def go():
        async def produce():
            for delay in frames_later:
                await asyncio.sleep(delay)
                count[0] += 1

        task = asyncio.create_task(produce())
        t0 = time.monotonic()
        await harness._drain(count, expected)
        task.cancel()
        return time.monotonic() - t0

    return asyncio.run(go())


def test_drain_returns_once_every_frame_came():
    assert _timed([5], 5) < 0.2


def test_drain_waits_for_a_stalled_stream_then_stops_when_frames_stop(monkeypatch):
    monkeypatch.setattr(harness, "DRAIN_QUIET_S", 0.2)
    # nothing for 0.4 s (longer than the quiet time: a training stall), then 3 frames
    count = [0]
    took = _timed(count, 10, frames_later=(0.4, 0.02, 0.02))
    assert count[0] == 3
    assert 0.6 <= took < 2.0


def test_drain_gives_up_after_its_limit(monkeypatch):
    monkeypatch.setattr(harness, "DRAIN_MAX_S", 0.3)
    took = _timed([0], 10)
    assert 0.3 <= took < 1.5
