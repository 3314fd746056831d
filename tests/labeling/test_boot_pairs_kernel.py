"""The boot's reading score kernel (kernels/boot_pairs.py) against its numpy twin."""

from __future__ import annotations

import numpy as np
import pytest

from labeler_service.labeling.kernels.boot_pairs import _pair_error
from tests.reference import pair_error


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
