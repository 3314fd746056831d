"""The booting labeler's install passes over a stacked window (kernels/stacked.py) give what
their per-frame numpy twins (tests/reference.py) give: labels given twice, out of range or
on several points of a track, frames without points."""

from __future__ import annotations

import numpy as np
import pytest

from labeler_service.errors import LabelerError
from labeler_service.labeling.frame import window_observations
from labeler_service.labeling.kernels.stacked import _spread_labels
from tests import reference


def _window(rng, n_frames=12, m=40):
    frames = []
    for k in range(n_frames):
        n = int(rng.integers(0, 30)) if k != 3 else 0  # frame 3: no point at all
        pts = rng.normal(0, 500, (n, 3)).astype(np.float32)
        lab = rng.integers(-3, m + 3, n)  # out of range both ways, repeats
        frames.append((k / 120.0, pts, lab))
    return frames


@pytest.mark.parametrize("seed", range(8))
def test_window_observations_matches_per_frame_reads(seed):
    rng = np.random.default_rng(seed)
    frames = _window(rng)
    mask = rng.random(40) < 0.5
    got = window_observations(frames, mask)
    assert np.array_equal(got, reference.window_obs(frames, mask), equal_nan=True)


def test_window_observations_keeps_the_checks_of_one_frame():
    pts = np.zeros((2, 3), dtype=np.float32)
    mask = np.ones(4, dtype=bool)
    with pytest.raises(LabelerError, match="labels for"):
        window_observations([(0.0, pts, np.array([0]))], mask)
    with pytest.raises(LabelerError, match="finite"):
        window_observations([(0.0, np.full((1, 3), np.nan), np.array([0]))], mask)
    with pytest.raises(LabelerError, match=r"\(N, 3\)"):
        window_observations([(0.0, np.zeros((1, 2)), np.array([0]))], mask)
    assert window_observations([], mask).shape == (0, 4, 3)


@pytest.mark.parametrize("seed", range(8))
def test_spread_labels_matches_per_frame_spread(seed):
    rng = np.random.default_rng(100 + seed)
    m, n_tracks = 30, 60
    win_ids, win_labels = [], []
    for k in range(10):
        n = int(rng.integers(0, 40)) if k != 2 else 0
        # track ids repeat within a frame at times (a split track), labels repeat too
        win_ids.append(rng.integers(0, n_tracks, n).astype(np.int64))
        lab = np.where(rng.random(n) < 0.4, rng.integers(0, m, n), -1).astype(np.int64)
        win_labels.append(lab)
    ids = np.unique(rng.integers(0, n_tracks, 25)).astype(np.int64)
    labels = np.where(rng.random(ids.size) < 0.7, rng.integers(0, m, ids.size), -1)
    want = reference.spread_labels(win_ids, win_labels, ids, labels.astype(np.int64))
    have = labels >= 0
    order = np.argsort(ids[have])
    starts = np.zeros(len(win_ids) + 1, dtype=np.int64)
    np.cumsum([w.size for w in win_ids], out=starts[1:])
    out = np.concatenate(win_labels)
    given = _spread_labels(ids[have][order], labels[have][order].astype(np.int64),
                           np.concatenate(win_ids), out, starts, m)  # fmt: skip
    got = [out[starts[k] : starts[k + 1]] for k in range(len(win_ids))]
    for g, w in zip(got, want, strict=True):
        assert np.array_equal(g, w)
    assert given == sum(
        int((w >= 0).sum() - (o >= 0).sum()) for w, o in zip(want, win_labels, strict=True)
    )
