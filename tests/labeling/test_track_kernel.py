"""The point tracker's matching kernel (kernels/track.py) against its KD-tree twin."""

from __future__ import annotations

import numpy as np
import pytest

from labeler_service.labeling.boot import PointTracker
from labeler_service.labeling.kernels.track import match_tracks
from tests.reference import match_tracks as match_tracks_ref


@pytest.mark.parametrize("seed", range(6))
def test_matches_twin_on_random_crowds(seed):
    rng = np.random.default_rng(seed)
    k = int(rng.integers(1, 400))
    pred = rng.uniform(-2000, 2000, (k, 3))
    pred[:, 2] = rng.uniform(0, 1800, k)
    # most points continue a prediction, some are new, some predictions end
    keep = rng.random(k) < 0.9
    pts = pred[keep] + rng.normal(0, rng.choice([1.0, 5.0, 20.0]), (int(keep.sum()), 3))
    pts = np.vstack([pts, rng.uniform(-2000, 2000, (int(rng.integers(0, 30)), 3))])
    pts = pts[rng.permutation(pts.shape[0])]
    gate = rng.choice([4.0, 10.0, 40.0], k)
    np.testing.assert_array_equal(match_tracks(pts, pred, gate), match_tracks_ref(pts, pred, gate))


def test_dense_cluster_and_degenerate_inputs():
    rng = np.random.default_rng(7)
    pred = rng.normal(0, 3.0, (60, 3))  # points closer than the gate: mutuality decides
    pts = pred + rng.normal(0, 1.0, pred.shape)
    gate = np.full(60, 30.0)
    got = match_tracks(pts, pred, gate)
    np.testing.assert_array_equal(got, match_tracks_ref(pts, pred, gate))
    assert got.max() >= 0
    empty = np.zeros((0, 3))
    assert match_tracks(empty, pred, gate).shape == (0,)
    np.testing.assert_array_equal(match_tracks(pts, empty, np.zeros(0)), np.full(60, -1))
    with pytest.raises(ValueError, match="gate"):
        match_tracks(pts, pred, np.zeros(3))


def test_tracker_keeps_ids_along_moving_points():
    rng = np.random.default_rng(1)
    base = rng.uniform(-1000, 1000, (50, 3))
    vel = rng.normal(0, 500, (50, 3))  # mm/s
    tr = PointTracker(120.0)
    first = None
    for f in range(10):
        order = rng.permutation(50)
        ids = tr.update((base + vel * f / 120.0)[order], f / 120.0)
        back = np.empty(50, dtype=np.int64)
        back[order] = ids
        if first is None:
            first = back
        np.testing.assert_array_equal(back, first)


@pytest.mark.parametrize("seed", range(4))
def test_track_history_matches_twin(seed):
    from labeler_service.labeling.boot import track_history
    from tests.reference import track_history as track_history_ref

    rng = np.random.default_rng(seed)
    tr = PointTracker(120.0)
    frames = []
    base = rng.uniform(-1000, 1000, (80, 3))
    for f in range(int(rng.integers(1, 24))):
        keep = rng.random(80) < 0.85  # points drop out and come back as new tracks
        pts = base[keep] + rng.normal(0, 0.5, (int(keep.sum()), 3)) + f
        pts = np.vstack([pts, rng.uniform(-1000, 1000, (int(rng.integers(0, 5)), 3))])
        pts = pts[rng.permutation(pts.shape[0])]
        frames.append((pts, tr.update(pts, f / 120.0)))
    frames.insert(0, (np.zeros((0, 3)), np.zeros(0, dtype=np.int64)))  # an empty frame
    ids = np.concatenate([frames[-1][1], [10_000, -5]])  # and ids never seen
    got = track_history(frames, ids)
    np.testing.assert_array_equal(got, track_history_ref(frames, ids))
    assert np.isfinite(got[:, -1, 0]).sum() == frames[-1][1].size
    assert track_history([], ids).shape == (ids.size, 0, 3)
