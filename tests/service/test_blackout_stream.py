"""A dropout (frames with no point at all) on a stream the plain labeler labels: nobody left,
so no recovery starts for it (``boot_config.blackout_hold_s``); before, 0.1 s of empty frames
started a recovery that rebooted every performer."""

from __future__ import annotations

import numpy as np
import pytest

from labeler_service.scenes.corrupt import CorruptionSpec, corrupt
from labeler_service.scenes.simulate import simulate_scene
from labeler_service.service.protocol import FrameMsg
from labeler_service.service.settings import load_settings
from labeler_service.service.stream import StreamState

RATE = 120.0
INIT = 30


@pytest.fixture(scope="module")
def frames():
    scene = simulate_scene(2, 3.0, "walk", seed=5, rate=RATE)
    return corrupt(scene, CorruptionSpec(protect_frames=INIT, seed=3))


def _run(frames, hold: float, empty: range) -> StreamState:
    settings = load_settings(
        labeler="online", metrics_port=None, warmup=False,
        streams=[{"name": "vol", "labeled_start": "labeler"}],
        boot_config={"blackout_hold_s": hold},
    )  # fmt: skip
    st = StreamState("vol", settings, settings.streams[0])
    names = frames.marker_names
    for f in range(INIT + 120):
        labels = None
        if f < INIT:
            labels = tuple(names[i] if i >= 0 else None for i in frames.truth[f])
        pts = frames.points[f]
        if f in empty:
            pts = np.zeros((0, 3), dtype=np.float32)
        st.process(FrameMsg("vol", f, float(frames.times[f]), pts, labels), 0)
    return st


def test_a_dropout_starts_no_recovery(frames):
    empty = range(INIT + 40, INIT + 56)  # 0.13 s of frames with no point
    st = _run(frames, 0.5, empty)
    assert st.recoveries == 0 and not st.recovering
    st0 = _run(frames, 0.0, empty)  # (counted as everyone leaving: a recovery)
    assert st0.recoveries == 1


def test_a_long_empty_run_is_everyone_leaving(frames):
    st = _run(frames, 0.5, range(INIT + 20, INIT + 100))  # 0.67 s
    assert st.recoveries == 1
