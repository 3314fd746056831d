"""A client that stamps ``t`` in milliseconds, through a running server (the unit test in
``tests/service/test_window_start.py`` calls ``StreamState.train`` directly). With the default
``max_time_step_s`` (1 s) the continuity check refuses such frames first (``time_jump``, the
stalled line asks "is t in milliseconds?"), so no labeler starts; with a larger
``max_time_step_s`` they reach the training, which fails with the rate line and status
``training_failed`` - a logged line, not a silent stream and not a labeler at 0.05 Hz."""

from __future__ import annotations

import asyncio
import logging

import numpy as np
from hostile.helpers import run, settings

from labeler_service.service.protocol import encode_frame
from labeler_service.service.server import Server
from labeler_service.service.transports.memory import MemoryTransport

RATE = 50.0


def _send_ms(caplog, **over) -> tuple[Server, str]:
    caplog.set_level(logging.INFO)
    rng = np.random.default_rng(0)
    base = rng.normal(scale=300.0, size=(12, 3)).astype(np.float32)
    labels = [f"s:m{i}" for i in range(12)]
    srv_out: list[Server] = []

    async def go():
        mem = MemoryTransport()
        async with Server(settings(labeler="baseline", **over), [mem]) as srv:
            srv_out.append(srv)
            for k in range(13):  # 12 labeled init frames, then an unlabeled one
                pts = base + np.float32(k)
                mem.inject(encode_frame("default", k, 1000.0 * k / RATE, pts,
                                        labels if k < 12 else None))  # fmt: skip
            async with asyncio.timeout(10):
                while srv.metrics.drops("training_failed") + srv.metrics.drops("time_jump") < (
                    1 if "max_time_step_s" in over else 12
                ):
                    await asyncio.sleep(0.05)
            await asyncio.sleep(0.2)

    run(go(), timeout=30)
    return srv_out[0], "\n".join(r.getMessage() for r in caplog.records)


def test_milliseconds_are_refused_by_continuity_before_any_training(caplog):
    srv, text = _send_ms(caplog)
    assert srv.metrics.drops("time_jump") == 12, text
    assert srv.metrics.drops("training_failed") == 0
    assert "labeler ready" not in text


def test_milliseconds_that_pass_continuity_fail_the_training_with_the_rate_line(caplog):
    srv, text = _send_ms(caplog, max_time_step_s=100.0)
    assert srv.metrics.drops("training_failed") == 1, text
    assert "training failed" in text
    assert "is 0.05 Hz: expected 1 to 10000 Hz (is t in seconds?" in text, text
    assert "labeler ready" not in text
