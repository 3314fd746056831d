"""The sweep index answers exactly what a scan of every point answers; its sort and slab bounds
are numpy's stable argsort and ``searchsorted``."""

from __future__ import annotations

import numpy as np
import pytest
import reference as ref

from labeler_service.labeling.kernels.gating import _candidates, _gate, _regate
from labeler_service.labeling.kernels.spatial import (
    _BUCKET_MAX,
    ANY,
    FREE,
    OWNED,
    _index,
    _lower,
    _nearest,
    _span,
    _upper,
)


def _cloud(rng, n, spread=4000.0):
    """Points spread like performers on a stage (wide in x and y), with exact duplicates and
    non-finite rows."""
    pts = rng.uniform(-spread / 2, spread / 2, (n, 3))
    pts[:, 2] = rng.uniform(0, 1800, n)
    pts[5] = pts[17]  # an exact duplicate: a tie at any centre
    pts[9] = np.nan
    pts[11, 1] = np.inf
    return pts.astype(np.float32)


def _brute_nearest(points, centre, lim2, owner, which, skip):
    best, bj = lim2, -1
    for j in range(points.shape[0]):
        if which == FREE and owner[j] >= 0:
            continue
        if which == OWNED and (owner[j] < 0 or j == skip):
            continue
        d2 = float(np.sum((points[j].astype(np.float64) - centre) ** 2))
        if d2 < best:  # in index order, so ties keep the lower index
            best, bj = d2, j
    return bj


@pytest.mark.parametrize("which", [ANY, FREE, OWNED])
def test_nearest_equals_a_full_scan(rng, which):
    points = _cloud(rng, 400)
    index = _index(points)
    owner = np.where(rng.random(400) < 0.4, 3, -1).astype(np.int32)
    for q in range(300):
        centre = points[q % 400].astype(np.float64) + rng.normal(0, 30, 3)
        if q % 7 == 0:
            centre = points[17].astype(np.float64)  # on the duplicate pair
        if not np.isfinite(centre).all():
            continue
        lim2 = float(rng.uniform(10, 300)) ** 2
        skip = int(rng.integers(0, 400))
        j, _ = _nearest(points, index, centre, lim2, owner, which, skip)
        assert j == _brute_nearest(points, centre, lim2, owner, which, skip)


def test_index_sorts_along_the_wider_axis_and_puts_non_finite_last(rng):
    points = _cloud(rng, 50)
    points[:, 1] *= 0.1  # x is now the wide axis
    index = _index(points)
    order, keys, axis = index.order, index.keys, index.axis  # a SweepIndex, read by name
    assert axis == 0
    assert np.all(np.diff(keys[np.isfinite(keys)]) >= 0)
    assert sorted(order.tolist()) == list(range(50))
    assert not np.isfinite(keys[-1])  # the NaN row sorts last


def test_gate_ties_go_to_the_lower_index_whatever_the_sweep_order():
    # two points mirrored about the prediction: the sweep meets point 1 (smaller x) first,
    # yet point 0 must be the first candidate, as in a scan in index order
    pred = np.zeros((1, 6))
    points = np.array([[10.0, 0, 0], [-10.0, 0, 0], [0, 0, 50.0]], dtype=np.float32)
    cand = np.zeros((1, 3), dtype=np.int32)
    cand_d2 = np.zeros((1, 3))
    ncand = np.zeros(1, dtype=np.int32)
    _gate(pred, np.ones(1), np.ones(1, bool), points, _index(points), 1e4, 3, cand, cand_d2, ncand)
    assert ncand[0] == 3 and cand[0].tolist() == [0, 1, 2]


@pytest.mark.parametrize("K", [1, 4])
def test_gate_and_regate_on_a_stage_equal_the_twins(rng, K):
    points = _cloud(rng, 600)
    m = 200
    pred = np.zeros((m, 6))
    pred[:, :3] = points[rng.integers(0, 600, m)] + rng.normal(0, 15, (m, 3))
    s = rng.uniform(20, 2000, m)
    active = rng.random(m) < 0.9
    index = _index(points)
    cand = np.zeros((m, K), dtype=np.int32)
    cand_d2 = np.zeros((m, K))
    ncand = np.zeros(m, dtype=np.int32)
    _gate(pred, s, active, points, index, 16.27, K, cand, cand_d2, ncand)
    for i, (js, _ds) in enumerate(ref.gate(pred, s, active, points, 16.27, K)):
        assert list(cand[i, : ncand[i]]) == js
    owner = np.where(rng.random(600) < 0.5, 1, -1).astype(np.int32)
    lost = rng.random(m) < 0.5
    radius = rng.uniform(20.0, 300.0, m)
    _regate(pred, lost, points, index, owner, radius, 16.27, K, cand, cand_d2, ncand)
    for i, js in ref.regate(pred, lost, points, owner, radius, 16.27, K).items():
        assert list(cand[i, : ncand[i]]) == js


@pytest.mark.parametrize("K", [1, 3, 8])
def test_gate_is_the_candidate_search_bit_for_bit(rng, K):
    """The gate's search over the key-ordered copy gives :func:`_candidates`'s result exactly:
    the same candidates in the same order, the same distances to the bit (a crowd with ghosts,
    exact duplicates, non-finite points and markers, inactive markers, narrow and wide gates)."""
    points = _cloud(rng, 400, spread=1500.0)
    m = 300
    pred = np.zeros((m, 6))
    pred[:, :3] = points[rng.integers(0, 400, m)] + rng.normal(0, 10, (m, 3))
    pred[:20, :3] = points[5]  # on the duplicate pair: exact ties
    pred[30, :3] = np.nan
    pred[31, 0] = np.inf
    s = rng.uniform(0.5, 3000, m)
    active = rng.random(m) < 0.9
    index = _index(points)
    got = [np.zeros((m, K), np.int32), np.zeros((m, K)), np.zeros(m, np.int32)]
    _gate(pred, s, active, points, index, 16.27, K, *got)
    want = [np.zeros((m, K), np.int32), np.zeros((m, K)), np.zeros(m, np.int32)]
    anyone = np.empty(0, np.int32)
    for i in range(m):
        if active[i]:
            sc, r = 1.0 / s[i], np.sqrt(16.27 * s[i])
            _candidates(i, pred[i], sc, r, points, index, anyone, False, 16.27, K, *want)
    assert np.array_equal(got[2], want[2])
    for i in range(m):
        c = got[2][i]
        assert np.array_equal(got[0][i, :c], want[0][i, :c])
        assert np.array_equal(got[1][i, :c], want[1][i, :c])


@pytest.mark.parametrize("seed", range(8))
def test_span_ends_are_searchsorted(seed):
    """A slab's ends are ``np.searchsorted``'s of its bounds: on ties, non-finite points, a far
    outlier and centres off either end."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 300))
    points = rng.normal(0, 400, (n, 3)).round(int(rng.integers(-1, 3)))  # many ties
    if seed % 2:
        points[rng.integers(n)] = [1e7, -1e7, 0.0]  # a far outlier
    points[rng.random(n) < 0.05, 0] = np.nan
    index = _index(points)
    keys = index.keys
    centres = [points[j] for j in range(n)] + list(rng.normal(0, 1500, (200, 3)))
    centres += [np.full(3, keys[0] + 8.0 * b) for b in range(-2, 40)]
    for c in centres:
        for radius in (0.0, 8.0, 30.0, 120.0, 1e4):
            lo, hi = _span(index, c, radius)
            if not np.isfinite(c[index.axis]):
                assert (lo, hi) == (0, 0)
                continue
            r = radius + 1e-6
            a = c[index.axis]
            assert lo == np.searchsorted(keys, a - r, side="left")
            assert hi == np.searchsorted(keys, a + r, side="right")


def test_span_of_no_finite_point():
    index = _index(np.full((4, 3), np.nan))
    assert _span(index, np.zeros(3), 100.0) == (0, 0)
    assert _span(_index(np.zeros((0, 3))), np.zeros(3), 100.0) == (0, 0)


def _frames(rng):
    """Point sets that exercise the buckets: crowds, ties, non-finite points, a far outlier
    (the fallback), one point, none, every point at one key."""
    crowd = rng.normal(0, 600, (490, 3))
    ties = np.round(rng.normal(0, 50, (200, 3)))  # many equal keys
    holes = crowd.copy()
    holes[rng.random(490) < 0.1] = np.nan
    holes[3] = [np.inf, 0.0, 0.0]
    far = crowd.copy()
    far[7, :2] = 1e7  # squeezes the rest into a few buckets
    same = np.zeros((60, 3))
    same[:, 2] = np.arange(60)
    return {"crowd": crowd, "ties": ties, "holes": holes, "far": far, "one": crowd[:1],
            "none": np.zeros((0, 3)), "same": same, "small": crowd[:5]}  # fmt: skip


@pytest.mark.parametrize("case", ["crowd", "ties", "holes", "far", "one", "none", "same", "small"])
def test_index_is_a_stable_sort_and_its_bounds_are_searchsorted(rng, case):
    pts = _frames(rng)[case]
    order, keys, axis, lo, inv_w, start = _index(pts)
    fin2 = np.where(np.isfinite(pts[:, :2]), pts[:, :2], np.nan)
    spread = np.nanmax(fin2, 0) - np.nanmin(fin2, 0) if len(pts) else [0, 0]
    assert axis == (1 if spread[1] > spread[0] else 0)
    raw = np.where(np.isfinite(pts[:, axis]), pts[:, axis], np.inf)
    want = np.argsort(raw, kind="mergesort")  # stable: ties by point index
    np.testing.assert_array_equal(order, want)
    np.testing.assert_array_equal(keys, raw[want])
    index = _index(pts)
    if case in ("far", "same"):
        assert start.size == 0  # crowded buckets: the binary-search fallback
    elif case == "crowd":
        assert start.size == len(pts) + 1 and np.diff(start).max() <= _BUCKET_MAX
    fin = keys[np.isfinite(keys)]
    probes = [-np.inf, np.inf, -1e9, 1e9]
    if fin.size:
        probes += list(fin) + list(fin + 1e-9) + list(fin - 1e-9)
        probes += list(rng.uniform(fin.min() - 100, fin.max() + 100, 300))
    for v in probes:
        assert _lower(index, v) == np.searchsorted(keys, v, side="left"), v
        assert _upper(index, v) == np.searchsorted(keys, v, side="right"), v
    if len(pts):
        c = np.nan_to_num(pts[0], nan=0.0, posinf=0.0)
        lo_k, hi_k = _span(index, c, 40.0)
        inside = np.flatnonzero(np.abs(keys - c[axis]) <= 40.0)
        assert (lo_k, hi_k) == ((inside[0], inside[-1] + 1) if inside.size else (lo_k, lo_k))
    assert _span(index, np.full(3, np.nan), 40.0) == (0, 0)
