"""The structure statistics of training (seed 003 Eq. 1-2) against a plain twin."""

from __future__ import annotations

import numpy as np

from labeler_service.labeling.training import pair_statistics


def _twin(pos: np.ndarray, min_pair_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """D = mean and A = (population) standard deviation of each pair's distance over the frames
    where both markers are seen; NaN for pairs seen together too rarely; 0 on the diagonal."""
    f, m, _ = pos.shape
    D = np.full((m, m), np.nan)
    A = np.full((m, m), np.nan)
    for i in range(m):
        for j in range(m):
            d = [np.linalg.norm(pos[k, i] - pos[k, j]) for k in range(f)
                 if np.isfinite(pos[k, i]).all() and np.isfinite(pos[k, j]).all()]  # fmt: skip
            if len(d) >= min_pair_frames:
                D[i, j], A[i, j] = np.mean(d), np.std(d)
    np.fill_diagonal(D, 0.0)
    np.fill_diagonal(A, 0.0)
    return D, A


def test_pair_statistics_equal_the_twin_with_missing_samples(rng):
    pos = rng.normal(scale=80.0, size=(40, 7, 3))
    pos += rng.normal(scale=3.0, size=pos.shape)
    pos[rng.random((40, 7)) < 0.25] = np.nan
    pos[:, 6] = np.nan
    pos[[3, 9], 6] = rng.normal(size=(2, 3))  # marker 6 seen twice only
    D, A = pair_statistics(pos, min_pair_frames=3)
    D2, A2 = _twin(pos, 3)
    np.testing.assert_allclose(D, D2, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(A, A2, rtol=1e-6, atol=1e-6)
    assert np.isnan(D[6, :6]).all() and D[6, 6] == 0.0


def test_a_rigid_pair_has_its_true_distance_and_no_deviation(rng):
    from scipy.spatial.transform import Rotation

    shape = rng.normal(scale=60.0, size=(4, 3))
    R = Rotation.random(30, random_state=1).as_matrix()
    pos = np.einsum("fij,mj->fmi", R, shape) + rng.normal(scale=100.0, size=(30, 1, 3))
    D, A = pair_statistics(pos)
    true = np.linalg.norm(shape[:, None] - shape[None], axis=2)
    np.testing.assert_allclose(D, true, atol=1e-9)
    np.testing.assert_allclose(A, 0.0, atol=1e-5)
