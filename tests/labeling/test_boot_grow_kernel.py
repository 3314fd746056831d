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
    # pairs of one trained body, rigid or not (the trilateration's own evidence)
    same = (sym < 0.3) | ((sym > 0.85) & (sym < 0.9))
    np.fill_diagonal(same, False)
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
    return assign, taken, pts, D, tol, bound, rigid, strict, link, same


@pytest.mark.parametrize("own", ["same", "rigid"])
@pytest.mark.parametrize("seed", range(12))
def test_grow_matches_twin(seed, own):
    assign, taken, *rest, same = _case(seed)
    evidence = same if own == "same" else rest[4]  # (rest[4]: rigid)
    a1, t1 = assign.copy(), taken.copy()
    a2, t2 = assign.copy(), taken.copy()
    _grow(a1, t1, *rest, evidence)
    grow(a2, t2, *rest, evidence)
    np.testing.assert_array_equal(a1, a2)
    np.testing.assert_array_equal(t1, t2)


def test_grow_places_hidden_markers():
    grown = 0
    for seed in range(12):
        assign, taken, *rest, _ = _case(seed)
        before = int((assign >= 0).sum())
        _grow(assign, taken, *rest, rest[4])
        grown += int((assign >= 0).sum()) - before
    assert grown > 0


def test_grow_joins_only_with_evidence_of_the_markers_own_body():
    """``own``: a marker joins only with a placed marker of its own trained body (rigid to it
    or not); pairs rigid by ``A`` alone (across a joint that never moved in training) do not
    suffice. With ``own = rigid`` every rigid partner counts."""
    rng = np.random.default_rng(3)
    X = rng.uniform(-150, 150, (6, 3))
    D = np.linalg.norm(X[:, None] - X[None], axis=2)
    rigid = ~np.eye(6, dtype=bool)
    rigid[4, 0] = rigid[0, 4] = False  # marker 0: in 4's body, not rigid to it (a joint)
    tol = np.full((6, 6), 5.0)
    bound = 50.0 + 0.5 * D
    link = np.full((6, 6), np.inf)
    pts = np.ascontiguousarray(X + rng.normal(0, 0.5, X.shape))
    start = np.array([0, 1, 2, 3, -1, -1])  # markers 4 and 5 to place
    for with_zero in (False, True):
        same = np.zeros((6, 6), dtype=bool)
        same[4, 5] = same[5, 4] = True  # a body of 4 and 5, both missing ...
        if with_zero:
            same[4, 0] = same[0, 4] = True  # ... and 0, placed
        strict = same & rigid
        a_own, t_own = start.copy(), np.zeros(6, dtype=bool)
        t_own[:4] = True
        a_any, t_any = a_own.copy(), t_own.copy()
        _grow(a_own, t_own, pts, D, tol, bound, rigid, strict, link, same)
        _grow(a_any, t_any, pts, D, tol, bound, rigid, strict, link, rigid)
        np.testing.assert_array_equal(a_any, np.arange(6))
        # with a placed marker of its body, 4 joins (from the rigid pairs) and brings 5 along
        np.testing.assert_array_equal(a_own, np.arange(6) if with_zero else start)
