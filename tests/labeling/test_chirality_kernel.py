"""The chirality kernel (``kernels/chirality.volume_stats``) against its numpy twin, and the
structure trainer's volume statistics against the kernel."""

from __future__ import annotations

import itertools

import numpy as np
import reference as ref

from labeler_service.labeling import structure
from labeler_service.labeling.kernels.chirality import volume_stats


def _frames(rng, f=30, m=7):
    pos = rng.normal(scale=80.0, size=(1, m, 3)) + rng.normal(scale=3.0, size=(f, m, 3))
    pos = pos.astype(np.float32)
    pos[rng.random((f, m)) < 0.15] = np.nan  # unseen markers
    pos[:, 6] = np.nan  # a marker never seen: its quadruples have no frame
    return pos


def test_volume_stats_matches_its_numpy_twin(rng):
    pos = _frames(rng)
    q = np.array(list(itertools.combinations(range(7), 4)), dtype=np.int64)
    n, frac, thick = volume_stats(pos, q, 0.1)
    rn, rfrac, rthick = ref.volume_stats(pos, q, 0.1)
    np.testing.assert_array_equal(n, rn)
    np.testing.assert_allclose(frac, rfrac, rtol=0, atol=1e-12)
    np.testing.assert_allclose(thick, rthick, rtol=1e-9, atol=1e-9)
    never = np.any(q == 6, axis=1)
    assert (n[never] == 0).all() and (thick[never] == 0).all() and (frac[never] == 0).all()
    assert (n[~never] > 0).all()
    # a mirrored frame reverses every sign: the fraction positive flips
    _, mirrored, _ = volume_stats(pos * np.array([-1, 1, 1], np.float32), q, 0.1)
    np.testing.assert_allclose(mirrored[~never], 1.0 - frac[~never], atol=1e-12)


def test_volume_stats_is_the_triple_product_of_signed_volumes(rng):
    """The kernel's sign counts are the ones the trainer's numpy triple product gives (the
    twin checks of ``twin_pairs`` still use it)."""
    pos = _frames(rng)
    q = np.array([[0, 1, 2, 3], [1, 2, 3, 4], [0, 2, 4, 6], [3, 1, 0, 2]], dtype=np.int64)
    det = structure._signed_volumes(pos, q)
    n, frac, _ = volume_stats(pos, q, structure.THICK_QUANTILE)
    seen = np.isfinite(det)
    np.testing.assert_array_equal(n, seen.sum(axis=0))
    np.testing.assert_array_equal(frac, (det > 0).sum(axis=0) / np.maximum(seen.sum(axis=0), 1))
