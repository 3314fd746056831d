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


@pytest.mark.parametrize("own", [True, False])
@pytest.mark.parametrize("seed", range(12))
def test_grow_matches_twin(seed, own):
    assign, taken, *rest = _case(seed)
    a1, t1 = assign.copy(), taken.copy()
    a2, t2 = assign.copy(), taken.copy()
    _grow(a1, t1, *rest, own)
    grow(a2, t2, *rest, own)
    np.testing.assert_array_equal(a1, a2)
    np.testing.assert_array_equal(t1, t2)


def test_grow_places_hidden_markers():
    grown = 0
    for seed in range(12):
        assign, taken, *rest = _case(seed)
        before = int((assign >= 0).sum())
        _grow(assign, taken, *rest, False)
        grown += int((assign >= 0).sum()) - before
    assert grown > 0


def test_grow_own_needs_a_partner_of_the_markers_body():
    """``own``: a marker joins only with a placed partner of its own trained body (``strict``);
    pairs rigid by ``A`` alone (across a joint that never moved in training) do not suffice."""
    rng = np.random.default_rng(3)
    X = rng.uniform(-150, 150, (6, 3))
    D = np.linalg.norm(X[:, None] - X[None], axis=2)
    rigid = ~np.eye(6, dtype=bool)
    tol = np.full((6, 6), 5.0)
    bound = 50.0 + 0.5 * D
    link = np.full((6, 6), np.inf)
    pts = np.ascontiguousarray(X + rng.normal(0, 0.5, X.shape))
    start = np.array([0, 1, 2, 3, -1, -1])  # markers 4 and 5 to place
    for strict_with, placed_own in ((None, False), (0, True)):
        strict = np.zeros((6, 6), dtype=bool)
        strict[4, 5] = strict[5, 4] = True  # one body of its own, 4 and 5, both missing
        if strict_with is not None:
            strict[4, strict_with] = strict[strict_with, 4] = True
        a_own, t_own = start.copy(), np.zeros(6, dtype=bool)
        t_own[:4] = True
        a_any, t_any = a_own.copy(), t_own.copy()
        _grow(a_own, t_own, pts, D, tol, bound, rigid, strict, link, True)
        _grow(a_any, t_any, pts, D, tol, bound, rigid, strict, link, False)
        np.testing.assert_array_equal(a_any, np.arange(6))
        # with a placed partner of its body, 4 joins and brings 5 (its own partner) along
        expect = np.arange(6) if placed_own else start
        np.testing.assert_array_equal(a_own, expect)
