"""The sweep index (kernels/spatial.py) against numpy: a stable argsort and searchsorted."""

from __future__ import annotations

import numpy as np
import pytest

from labeler_service.labeling.kernels.spatial import _BUCKET_MAX, _index, _lower, _span, _upper


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
