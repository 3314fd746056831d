"""The closest-point baseline: nearest-first collisions, gated misses, supervised frames."""

from __future__ import annotations

import numpy as np
import pytest

from labeler_service.errors import LabelerError
from labeler_service.labeling.baseline import ClosestPointLabeler
from labeler_service.labeling.frame import MarkerState


def _pts(*xyz: tuple[float, float, float]) -> np.ndarray:
    return np.asarray(xyz, dtype=np.float32)


def test_supervised_frame_sets_positions_then_tracks() -> None:
    lab = ClosestPointLabeler(("a", "b"), rate=100.0)
    out = lab.process(_pts((0, 0, 0), (100, 0, 0)), 0.0, np.array([1, 0]))
    assert out.point_labels.tolist() == [1, 0]
    out = lab.process(_pts((98, 1, 0), (2, 0, 0)), 0.01)
    assert out.point_labels.tolist() == [0, 1]
    assert out.state.tolist() == [MarkerState.OBSERVED] * 2


def test_collision_goes_to_the_nearest_label() -> None:
    lab = ClosestPointLabeler(("a", "b"), rate=100.0, min_gate_mm=50)
    lab.process(_pts((0, 0, 0), (20, 0, 0)), 0.0, np.array([0, 1]))
    # One point between them, nearer to b: b takes it, a is missing (no other point in gate).
    out = lab.process(_pts((15, 0, 0)), 0.01)
    assert out.point_labels.tolist() == [1]
    assert out.state.tolist() == [MarkerState.MISSING, MarkerState.OBSERVED]
    assert np.isnan(out.positions[0]).all()


def test_gate_grows_with_time_since_seen() -> None:
    lab = ClosestPointLabeler(("a",), rate=100.0, max_speed_mm_s=1000, min_gate_mm=10)
    lab.process(_pts((0, 0, 0)), 0.0, np.array([0]))
    assert lab.process(_pts((100, 0, 0)), 0.01).point_labels.tolist() == [-1]
    # 0.2 s later the gate is 200 mm: the same point is taken.
    assert lab.process(_pts((100, 0, 0)), 0.2).point_labels.tolist() == [0]


def test_empty_frames_and_bad_input() -> None:
    lab = ClosestPointLabeler(("a",), rate=100.0)
    out = lab.process(np.empty((0, 3), np.float32), 0.0)
    assert out.point_labels.shape == (0,) and out.state.tolist() == [MarkerState.MISSING]
    with pytest.raises(LabelerError, match="2 labels for 1 points"):
        lab.process(_pts((0, 0, 0)), 0.0, np.array([0, 0]))
    with pytest.raises(ValueError):
        ClosestPointLabeler((), rate=100.0)


def test_matches_brute_force_greedy(rng) -> None:
    """Against a naive twin: all pairs sorted by distance, taken greedily."""
    m = 30
    last = rng.uniform(0, 300, size=(m, 3)).astype(np.float32)
    lab = ClosestPointLabeler(tuple(f"m{i}" for i in range(m)), rate=120.0, min_gate_mm=40)
    lab.process(last, 0.0, np.arange(m))
    pts = (last[rng.permutation(m)[:25]] + rng.normal(0, 8, size=(25, 3))).astype(np.float32)
    got = lab.process(pts, 1 / 120).point_labels
    gate = max(40, 4000 / 120)
    d = np.linalg.norm(last.astype(np.float64)[:, None] - pts[None], axis=2)
    want = np.full(25, -1)
    used = set()
    for flat in np.argsort(d, axis=None, kind="stable"):
        i, j = divmod(int(flat), 25)
        if d[i, j] > gate:
            break
        if i in used or want[j] >= 0:
            continue
        used.add(i)
        want[j] = i
    np.testing.assert_array_equal(got, want)
