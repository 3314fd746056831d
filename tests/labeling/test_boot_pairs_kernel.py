"""The boot's reading score kernel (kernels/boot_pairs.py) against its numpy twin."""

from __future__ import annotations

import numpy as np
import pytest

from labeler_service.labeling.kernels.boot_pairs import _constancy_counts, _pair_error
from tests.reference import constancy_counts, pair_error


def _tables(rng, m):
    D = rng.uniform(50, 600, (m, m))
    D = (D + D.T) / 2
    D[rng.random((m, m)) < 0.1] = np.nan  # pairs never seen together
    scale = rng.uniform(2, 40, (m, m))
    gauss = rng.random((m, m)) < 0.4
    use = rng.random((m, m)) < 0.8
    return D, scale, np.log(scale), gauss, use


@pytest.mark.parametrize("seed", range(8))
def test_pair_error_matches_twin(seed):
    rng = np.random.default_rng(seed)
    m, n = int(rng.integers(4, 60)), int(rng.integers(10, 200))
    D, scale, logs, gauss, use = _tables(rng, m)
    pts = rng.uniform(-800, 800, (n, 3))
    assign = np.full(m, -1, dtype=np.int64)
    placed = rng.permutation(m)[: int(rng.integers(0, m))]
    assign[placed] = rng.permutation(n)[: placed.size]
    k = int(rng.integers(1, min(m, 8) + 1))
    markers = rng.permutation(m)[:k].astype(np.int64)  # some placed in assign too (excluded)
    points = rng.permutation(n)[:k].astype(np.int64)
    got = _pair_error(D, scale, logs, gauss, use, markers, points, assign, pts, 4.0)
    want = pair_error(D, scale, logs, gauss, use, markers, points, assign, pts, 4.0)
    assert got == pytest.approx(want, rel=1e-9, abs=1e-9)


def test_pair_error_degenerate():
    rng = np.random.default_rng(1)
    D, scale, logs, gauss, use = _tables(rng, 5)
    pts = rng.uniform(-100, 100, (6, 3))
    pts[2] = np.nan  # a non-finite distance carries no evidence
    none = np.full(5, -1, dtype=np.int64)
    one = np.array([0], dtype=np.int64)
    assert _pair_error(D, scale, logs, gauss, use, one, one, none, pts, 4.0) == 0.0
    mk, pp = np.array([0, 1], dtype=np.int64), np.array([2, 3], dtype=np.int64)
    assign = np.array([-1, -1, 4, 5, 1], dtype=np.int64)
    assert _pair_error(D, scale, logs, gauss, use, mk, pp, assign, pts, 4.0) == pytest.approx(
        pair_error(D, scale, logs, gauss, use, mk, pp, assign, pts, 4.0)
    )


@pytest.mark.parametrize("seed", range(8))
def test_constancy_counts_match_twin(seed):
    rng = np.random.default_rng(seed)
    N, W, n = int(rng.integers(3, 80)), int(rng.integers(1, 25)), int(rng.integers(1, 20))
    n = min(n, N)
    hist = rng.normal(0, 300, (N, W, 3))
    hist[rng.random((N, W)) < 0.15] = np.nan  # untracked frames give no sample
    pts = rng.permutation(N)[:n].astype(np.int64)
    d0 = np.linalg.norm(hist[pts][:, None, 0] - hist[pts][None, :, 0], axis=2)
    # D at a frame's exact distance (a zero tolerance there is the edge: not off)
    D = np.where(np.isfinite(d0), d0, rng.uniform(50, 600, (n, n)))
    tol = rng.uniform(0, 20, (n, n))
    tol[rng.random((n, n)) < 0.3] = 0.0
    strict = rng.random((n, n)) < 0.6
    seen, bad = _constancy_counts(hist, pts, D, tol, strict)
    want_seen, want_bad = constancy_counts(hist, pts, D, tol, strict)
    np.testing.assert_array_equal(seen, want_seen)
    np.testing.assert_array_equal(bad, want_bad)


def test_constancy_counts_degenerate():
    hist = np.full((3, 4, 3), np.nan)  # nothing tracked: nothing seen
    pts = np.array([0, 1, 2], dtype=np.int64)
    D, tol = np.zeros((3, 3)), np.ones((3, 3))
    seen, bad = _constancy_counts(hist, pts, D, tol, np.ones((3, 3), dtype=bool))
    assert seen.tolist() == [0, 0, 0] and bad.tolist() == [0, 0, 0]
    hist = np.zeros((2, 3, 3))
    hist[1, :, 0] = [10.0, 10.0, 30.0]  # 10 mm apart twice, then 30 mm
    two = np.array([0, 1], dtype=np.int64)
    strict = np.array([[False, True], [True, False]])
    seen, bad = _constancy_counts(hist, two, np.full((2, 2), 10.0), np.full((2, 2), 5.0), strict)
    assert seen.tolist() == [3, 3] and bad.tolist() == [1, 1]
    seen, bad = _constancy_counts(hist, two[:0], D[:0, :0], tol[:0, :0], strict[:0, :0])
    assert seen.size == 0 and bad.size == 0


@pytest.mark.parametrize("seed", range(8))
def test_swap_gains_match_twin(seed):
    from labeler_service.labeling.kernels.boot_pairs import _swap_gains
    from tests.reference import swap_gains

    rng = np.random.default_rng(seed)
    m = int(rng.integers(3, 50))
    D, scale, logs, gauss, use = _tables(rng, m)
    have = np.sort(rng.permutation(m)[: int(rng.integers(2, m + 1))]).astype(np.int64)
    pts = rng.uniform(-600, 600, (have.size, 3))
    pts[rng.random(have.size) < 0.15] = np.nan  # untracked points
    ka, kb = (x.astype(np.int64) for x in np.triu_indices(have.size, 1))
    got = _swap_gains(D, scale, logs, gauss, use, have, ka, kb, pts, 4.0)
    want = swap_gains(D, scale, logs, gauss, use, have, ka, kb, pts, 4.0)
    assert np.array_equal(np.isnan(got), np.isnan(want))
    ok = ~np.isnan(want)
    assert got[ok] == pytest.approx(want[ok], rel=1e-9, abs=1e-9)
    assert ok.any() or np.isnan(pts[:, 0]).sum() >= have.size - 1
