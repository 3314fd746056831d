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


def test_a_slow_service_start_is_waited_for_with_notes_then_refused(tmp_path, monkeypatch, capsys):
    """A first start compiles the kernels: on a busy 2-core machine it passed the 180 s the
    harness waited, and the demo failed. It now waits longer and says what it waits for."""
    import sys

    import pytest

    from labeler_service.errors import MocapError

    slow = tmp_path / "slow-python"
    slow.write_text("#!/bin/sh\nexec sleep 30\n")  # a service that never says ready
    slow.chmod(0o755)
    monkeypatch.setattr(sys, "executable", str(slow))
    monkeypatch.setattr(harness, "READY_NOTE_S", 0.2)
    assert harness.ServiceProcess({}, tmp_path).ready_timeout >= 600

    async def start() -> None:
        async with harness.ServiceProcess({}, tmp_path / "svc", ready_timeout=0.7):
            pass

    with pytest.raises(MocapError, match=r"did not become ready within 0.7 s"):
        asyncio.run(start())
    assert capsys.readouterr().err.count("still waiting for the service to start") == 3
