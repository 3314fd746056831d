"""The bench harness waits for every frame the service publishes: a stream started from a
model publishes its labeled first frames too, and the wait ended that many frames short, so
the last frame of ``bench latency`` (default ``--start model``) arrived after the subscriber
stopped: 480 sent, 479 received, "frames were lost", and no counter named the loss."""

from __future__ import annotations

import asyncio

from labeler_service.testing.harness import (
    run_pipeline,
    service_settings,
    simulated_frames,
    train_model_file,
)


def test_a_model_started_run_receives_every_frame_it_sent(tmp_path):
    frames = simulated_frames(2, 1.5, 120.0, 0, "hug")
    model = train_model_file(frames, 50, tmp_path / "m.json")
    cfg = {"name": "bench", "rate": frames.rate, "model": str(model)}
    settings = service_settings("udp", cfg, 5.0, labeler="online", boot=False)
    res = asyncio.run(run_pipeline(frames, settings, tmp_path, stream="bench", init_frames=5,
                                   max_frames=180))  # fmt: skip
    assert res.sent == 180
    assert len(res.received) == 180, sorted({r.msg.seq for r in res.received})[-5:]
    assert res.service_returncode == 0
