"""Horn's method (numba kernel vs numpy twin), log map, sign continuity, triangle features."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from shoulder.reference import horn_reference

from offline.shoulder.rotations import (
    continuous_sign,
    exp_map,
    fill_gaps,
    horn_quaternions,
    log_map,
    triangle_features,
)


def _wxyz(rot: Rotation) -> np.ndarray:
    q = rot.as_quat()  # x, y, z, w
    q = np.concatenate([q[..., 3:], q[..., :3]], axis=-1)
    return q * np.where(q[..., :1] < 0, -1.0, 1.0)


def test_horn_recovers_exact_rotations(rng):
    ref = rng.normal(scale=20.0, size=(30, 3, 3))
    rots = Rotation.random(50, random_state=1)
    cur = np.einsum("fij,tvj->ftvi", rots.as_matrix(), ref) + rng.normal(size=(50, 1, 1, 3)) * 100
    q = horn_quaternions(ref, cur)
    np.testing.assert_allclose(q, np.repeat(_wxyz(rots)[:, None], 30, axis=1), atol=1e-9)


def test_horn_kernel_matches_numpy_twin_on_noisy_nan_and_degenerate(rng):
    ref = rng.normal(scale=15.0, size=(12, 3, 3))
    ref[0] = [[0, 0, 0], [10, 0, 0], [20, 0, 0]]  # collinear: rotation about the line undefined
    ref[1] = [[0, 0, 0], [0, 0, 0], [0, 0, 0]]  # all three vertices coincide
    rots = Rotation.random(40, random_state=2).as_matrix()
    cur = np.einsum("fij,tvj->ftvi", rots, ref) + rng.normal(scale=2.0, size=(40, 12, 3, 3))
    cur[3, 5, 1] = np.nan
    cur[7, :, 0] = np.nan
    q = horn_quaternions(ref, cur)
    q_ref = horn_reference(ref, cur)
    assert np.array_equal(np.isnan(q), np.isnan(q_ref))
    good = ~np.isnan(q_ref[..., 0])
    good[:, :2] = False  # degenerate triangles: any unit quaternion is a valid answer
    # compare the rotations (q and -q are the same rotation)
    dot = np.abs(np.einsum("fti,fti->ft", q, q_ref))[good]
    assert dot.min() > 1 - 1e-8
    norms = np.linalg.norm(q[:, :2], axis=-1)
    np.testing.assert_allclose(norms[np.isfinite(norms)], 1.0, atol=1e-9)


def test_horn_validates_shapes():
    with pytest.raises(ValueError, match="ref must be"):
        horn_quaternions(np.zeros((3, 3)), np.zeros((1, 1, 3, 3)))
    with pytest.raises(ValueError, match="cur must be"):
        horn_quaternions(np.zeros((2, 3, 3)), np.zeros((1, 3, 3, 3)))
    with pytest.raises(ValueError, match="NaN"):
        horn_quaternions(np.full((1, 3, 3), np.nan), np.zeros((1, 1, 3, 3)))


def test_log_map_is_half_angle_axis_and_inverts_exp():
    rots = Rotation.random(100, random_state=3)
    q = _wxyz(rots)
    v = log_map(q)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), rots.magnitude() / 2, atol=1e-12)
    np.testing.assert_allclose(exp_map(v), q, atol=1e-12)
    np.testing.assert_allclose(log_map(np.array([1.0, 0, 0, 0])), 0.0)
    assert np.isnan(log_map(np.full(4, np.nan))).all()


def test_continuous_sign_follows_a_rotation_through_180_degrees():
    angles = np.linspace(0, 1.9 * np.pi, 200)  # past 180 deg about z
    q = np.stack([np.cos(angles / 2), 0 * angles, 0 * angles, np.sin(angles / 2)], 1)
    q = q * np.where(q[:, :1] < 0, -1.0, 1.0)  # what Horn returns: w >= 0, a jump at 180 deg
    fixed = continuous_sign(q[:, None, :], start=0)[:, 0]
    steps = np.einsum("fi,fi->f", fixed[1:], fixed[:-1])
    assert steps.min() > 0.99
    v = log_map(fixed)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), angles / 2, atol=1e-9)


def test_continuous_sign_drops_an_impossible_jump():
    q = np.tile([1.0, 0.0, 0.0, 0.0], (10, 1))
    q[5] = [0.0, 1.0, 0.0, 0.0]  # 180 deg in one frame: an ill-conditioned estimate
    fixed = continuous_sign(q[:, None, :], start=0)[:, 0]
    assert np.isnan(fixed[5]).all()
    assert np.isfinite(np.delete(fixed, 5, axis=0)).all()


def test_fill_gaps_interpolates_and_holds_ends():
    x = np.array([[np.nan, 1.0], [1.0, np.nan], [np.nan, np.nan], [3.0, 4.0], [np.nan, np.nan]])
    out = fill_gaps(x)
    np.testing.assert_allclose(out[:, 0], [1, 1, 2, 3, 3])
    np.testing.assert_allclose(out[:, 1], [1, 2, 3, 4, 4])
    assert (fill_gaps(np.full((3, 1), np.nan)) == 0).all()


def test_triangle_features_equal_for_rigid_triangles(rng):
    pts = rng.normal(scale=30.0, size=(6, 3))
    rots = Rotation.from_rotvec(np.outer(np.linspace(0, 2.5, 50), [0.3, 1.0, 0.2])).as_matrix()
    pos = np.einsum("fij,mj->fmi", rots, pts)
    pos[10, 2] = np.nan
    faces = np.array([[0, 1, 2], [3, 4, 5], [0, 3, 5]])
    X = triangle_features(pos, pts, faces)
    assert X.shape == (3, 150)
    assert np.isfinite(X).all()
    np.testing.assert_allclose(X[0], X[1], atol=1e-6)  # interpolated frame 10 included
    np.testing.assert_allclose(X[1], X[2], atol=1e-9)
