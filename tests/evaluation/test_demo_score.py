"""``demo`` scores what the subscriber received with the scorer of ``evaluate``."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from synthetic import moving_clusters

from labeler_service.cli.demo import score
from labeler_service.labeling.frame import MarkerState
from labeler_service.scenes.corrupt import CorruptionSpec, corrupt


def _received(frames, seq, names, swap=None, recovered_error=0.0):
    """The message the service would publish for frame ``seq`` (markers in ``names`` order)."""
    idx = {n: i for i, n in enumerate(frames.marker_names)}
    m = len(names)
    state = np.zeros(m, np.uint8)
    pos = np.full((m, 3), np.nan, np.float32)
    truth, pts = frames.truth[seq], frames.points[seq]
    for j, name in enumerate(names):
        col = idx[name]
        if swap and col in swap:
            col = swap[col]
        hit = np.flatnonzero(truth == col)
        if hit.size:
            state[j], pos[j] = MarkerState.OBSERVED, pts[hit[0]]
        elif frames.removed[seq, idx[name]]:
            state[j] = MarkerState.RECOVERED
            pos[j] = frames.positions[seq, idx[name]] + np.float32(recovered_error)
    msg = SimpleNamespace(seq=seq, state=state, positions=pos)
    return SimpleNamespace(msg=msg, names=names)


def test_received_frames_scored_like_evaluate(rng) -> None:
    cap = moving_clusters(rng, frames=80)
    frames = corrupt(cap, CorruptionSpec(gaps=1, gap_frames=5, ghosts=1.0, protect_frames=20))
    names = tuple(reversed(frames.marker_names))  # the service may order markers differently
    received = [
        _received(frames, f, names, swap={0: 1, 1: 0} if 40 <= f < 50 else None,
                  recovered_error=2.0)
        for f in range(20, 80)
        if f != 60  # lost on the way
    ]  # fmt: skip
    s = score(frames, received, init_frames=20)
    lost = int((frames.truth[60] >= 0).sum())
    swapped = sum(int(np.isin([0, 1], frames.truth[f]).all()) * 2 for f in range(40, 50))
    assert s.errors["unlabeled"] == lost
    assert s.errors["same_subject"] == swapped > 0
    assert s.accuracy == (s.visible - lost - swapped) / s.visible
    assert s.per_frame_accuracy[60] == 0.0
    assert s.max_swap_frames == 10
    assert s.ghost_labeled_rate == 0.0
    assert abs(s.recovery_mean_mm - 2.0 * np.sqrt(3)) < 1e-3
    removed_lost = int(frames.removed[60].sum())
    assert s.recovery_rate == (s.removed - removed_lost) / s.removed
