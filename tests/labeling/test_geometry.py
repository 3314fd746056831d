"""The public rigid fits (labeling/geometry.py) against plain-numpy twins, and their validation."""

from __future__ import annotations

import numpy as np
import pytest
from reference import kabsch as kabsch_reference
from scipy.spatial.transform import Rotation

from labeler_service.labeling.geometry import aligned_mean, horn_quaternions, kabsch


def test_kabsch_matches_the_svd_twin_and_recovers_exact_motions(rng):
    for _ in range(20):
        src = rng.normal(scale=100.0, size=(int(rng.integers(3, 9)), 3))
        R0 = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
        t0 = rng.normal(scale=500.0, size=3)
        noisy = src @ R0.T + t0 + rng.normal(scale=1.0, size=src.shape)
        R, t = kabsch(src, noisy)
        R_ref, t_ref = kabsch_reference(src, noisy)
        np.testing.assert_allclose(R, R_ref, atol=1e-8)
        np.testing.assert_allclose(t, t_ref, atol=1e-6)
        R, t = kabsch(src, src @ R0.T + t0)
        np.testing.assert_allclose(R, R0, atol=1e-9)
        np.testing.assert_allclose(t, t0, atol=1e-6)


def test_kabsch_validates_once_and_names_the_argument():
    with pytest.raises(ValueError, match="src must be 2-D"):
        kabsch(np.zeros((3, 2)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="same shape"):
        kabsch(np.zeros((4, 3)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="at least 3 points"):
        kabsch(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="dst contains NaN"):
        kabsch(np.zeros((3, 3)), np.full((3, 3), np.nan))


def test_aligned_mean_is_the_mean_of_the_fitted_frames(rng):
    shape = rng.normal(scale=80.0, size=(5, 3))
    frames = []
    for _ in range(6):
        R0 = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
        frames.append(shape @ R0.T + rng.normal(scale=300.0, size=3)
                      + rng.normal(scale=0.5, size=shape.shape))  # fmt: skip
    frames = np.stack(frames)
    ref = frames[0].copy()
    expected = np.mean([f @ R.T + t for f in frames for R, t in [kabsch_reference(f, ref)]], axis=0)
    np.testing.assert_allclose(aligned_mean(frames, ref), expected, atol=1e-6)
    with pytest.raises(ValueError, match="must be"):
        aligned_mean(frames[:, :4], ref)


def test_horn_quaternions_of_point_sets_larger_than_triangles(rng):
    ref = rng.normal(scale=50.0, size=(4, 5, 3))
    rots = Rotation.random(4, random_state=7)
    cur = np.stack([ref[i] @ rots[i].as_matrix().T + 10.0 * i for i in range(4)])[None]
    cur[0, 2, 1] = np.nan
    q = horn_quaternions(ref, cur)
    want = rots.as_quat(scalar_first=True)
    want *= np.sign(want[:, :1])
    ok = [0, 1, 3]
    np.testing.assert_allclose(q[0, ok], want[ok], atol=1e-9)
    assert np.isnan(q[0, 2]).all()
    with pytest.raises(ValueError, match="k >= 3"):
        horn_quaternions(np.zeros((1, 2, 3)), np.zeros((1, 1, 2, 3)))
