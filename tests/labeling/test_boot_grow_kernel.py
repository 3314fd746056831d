"""The boot's trilateration kernel (kernels/boot_grow.py) against its numpy twin."""

from __future__ import annotations

import numpy as np
import pytest

from labeler_service.labeling.kernels.boot_grow import _grow
from tests.reference import grow


def _case(seed):
    rng = np.random.default_rng(seed)
    m = int(rng.integers(6, 40))
    X = rng.uniform(-300, 300, (m, 3))
    D = np.linalg.norm(X[:, None] - X[None], axis=2)
    sym = rng.random((m, m))
    sym = (sym + sym.T) / 2
    rigid = sym < 0.5
    np.fill_diagonal(rigid, False)
    strict = rigid & (sym < 0.3)
    tol = np.where(rigid, rng.uniform(3, 10), np.inf)
    bound = np.where(sym > 0.9, np.inf, 50.0 + 0.5 * D)
    link = np.where(~rigid & (sym < 0.8), 30.0, np.inf)
    D[(sym > 0.95) & ~rigid] = np.nan  # pairs never seen together
    pts = X + rng.normal(0, rng.choice([0.5, 3.0]), X.shape)
    clutter = rng.uniform(-400, 400, (int(rng.integers(0, 80)), 3))
    pts = np.vstack([pts, clutter])
    perm = rng.permutation(pts.shape[0])
    pts = np.ascontiguousarray(pts[perm])
    where = np.argsort(perm)[:m]  # the point of each marker
    assign = np.full(m, -1, dtype=np.int64)
    placed = rng.random(m) < rng.uniform(0.3, 0.8)
    assign[placed] = where[placed]
    taken = np.zeros(pts.shape[0], dtype=bool)
    taken[assign[assign >= 0]] = True
    taken[rng.random(pts.shape[0]) < 0.05] = True  # other subjects' points
    return assign, taken, pts, D, tol, bound, rigid, strict, link


@pytest.mark.parametrize("seed", range(12))
def test_grow_matches_twin(seed):
    assign, taken, *rest = _case(seed)
    a1, t1 = assign.copy(), taken.copy()
    a2, t2 = assign.copy(), taken.copy()
    _grow(a1, t1, *rest)
    grow(a2, t2, *rest)
    np.testing.assert_array_equal(a1, a2)
    np.testing.assert_array_equal(t1, t2)


def test_grow_places_hidden_markers():
    grown = 0
    for seed in range(12):
        assign, taken, *rest = _case(seed)
        before = int((assign >= 0).sum())
        _grow(assign, taken, *rest)
        grown += int((assign >= 0).sum()) - before
    assert grown > 0
