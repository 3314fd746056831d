"""The boot's anchor-triangle kernels (kernels/boot_anchor.py) against their numpy twins."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from labeler_service.labeling.kernels.boot_anchor import _anchor_predict, _join_triangles
from tests.reference import anchor_predict, join_triangles


def _edges(rng, n, m):
    """``m`` random directed edges among ``n`` points (repeats and self-edges allowed)."""
    return rng.integers(0, n, m).astype(np.int64), rng.integers(0, n, m).astype(np.int64)


@pytest.mark.parametrize("seed", range(10))
def test_join_triangles_matches_twin(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 40))
    a1, b1 = _edges(rng, n, int(rng.integers(0, 120)))
    a2, b2 = _edges(rng, n, int(rng.integers(1, 120)))
    a3, b3 = _edges(rng, n, int(rng.integers(1, 200)))
    o2 = np.argsort(a2, kind="stable")
    keys3 = np.sort(a3 * n + b3)
    got = _join_triangles(a1, b1, a2[o2], b2[o2], keys3, np.int64(n))
    want = join_triangles(a1, b1, a2[o2], b2[o2], keys3, n)
    np.testing.assert_array_equal(got, want.reshape(-1, 3))
    # every triple closes: its three edges are in the three lists
    e1, e2, e3 = set(zip(a1, b1, strict=True)), set(zip(a2, b2, strict=True)), set(keys3)
    for p, q, r in got:
        assert (p, q) in e1 and (p, r) in e2 and q * n + r in e3 and q != r


def test_join_triangles_without_a_closing_edge():
    a = np.array([0, 1], dtype=np.int64)
    b = np.array([1, 2], dtype=np.int64)
    got = _join_triangles(a, b, a, b, np.zeros(0, dtype=np.int64), np.int64(3))
    assert got.shape == (0, 3)


@pytest.mark.parametrize("seed", range(6))
def test_anchor_predict_places_a_moved_body(seed):
    """Triples that are the body's anchor triangle moved rigidly (plus noise) predict the
    other members where the same motion puts them, as the SVD twin does."""
    rng = np.random.default_rng(seed)
    k = int(rng.integers(3, 9))
    shape = rng.normal(0, 80, (k, 3))
    tri = rng.choice(k, 3, replace=False)
    C = int(rng.integers(1, 30))
    Rs = Rotation.random(C, random_state=seed).as_matrix()
    ts = rng.uniform(-1000, 1000, (C, 3))
    moved = np.einsum("cij,kj->cki", Rs, shape) + ts[:, None, :]
    pts = moved[:, tri].reshape(-1, 3) + rng.normal(0, 0.5, (3 * C, 3))
    trip = np.arange(3 * C, dtype=np.int64).reshape(C, 3)
    got = _anchor_predict(np.ascontiguousarray(shape[tri]), shape, pts, trip)
    np.testing.assert_allclose(got, anchor_predict(shape[tri], shape, pts, trip), atol=1e-6)
    assert np.abs(got - moved).max() < 20.0  # (noise on the anchors, lever arm of the rest)
    exact = _anchor_predict(
        np.ascontiguousarray(shape[tri]), shape, moved[:, tri].reshape(-1, 3), trip
    )
    np.testing.assert_allclose(exact, moved, atol=1e-6)
