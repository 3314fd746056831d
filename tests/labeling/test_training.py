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


def _markers_with_a_swinging_hand(rng, frames: int = 5) -> np.ndarray:
    """Three rigid torso markers and a hand that stays near them but once swings 800 mm away
    (a 5-frame window of a tennis serve at 12.5 Hz): its distances vary as much as their mean."""
    torso = np.array([[0.0, 0.0, 1000.0], [150.0, 0.0, 1000.0], [0.0, 120.0, 1100.0]])
    pos = np.repeat(torso[None], frames, axis=0) + rng.normal(scale=0.5, size=(frames, 3, 3))
    hand = torso[0] + np.array([40.0, 30.0, 0.0])
    hands = np.repeat(hand[None], frames, axis=0)
    hands[-1] += np.array([800.0, 0.0, 0.0])
    return np.concatenate([pos, hands[:, None, :]], axis=1)


def test_a_trained_template_stays_within_the_ranges_every_model_keeps(rng):
    from labeler_service.labeling.templates import LabelerModel
    from labeler_service.labeling.training import model_pair_statistics, train_subject

    pos = _markers_with_a_swinging_hand(rng)
    _, A_raw = pair_statistics(pos)
    D, A = model_pair_statistics(pos)
    assert A_raw[0, 3] >= D[0, 3]  # the raw deviation is not below the distance ...
    assert A[0, 3] < D[0, 3] and A[0, 3] > 0.99 * D[0, 3]  # ... the template's is, just
    np.testing.assert_array_equal(A[:3, :3], A_raw[:3, :3])  # rigid pairs untouched
    tpl = train_subject("P", ["a", "b", "c", "hand"], pos, 12.5)
    LabelerModel(rate=12.5, subjects=[tpl])  # validates (it raised before)


def test_one_point_under_two_names_is_an_unknown_pair(rng):
    from labeler_service.labeling.templates import LabelerModel
    from labeler_service.labeling.training import model_pair_statistics, train_subject

    pos = _markers_with_a_swinging_hand(rng, frames=12)[:, :3]
    pos = np.concatenate([pos, pos[:, :1]], axis=1)  # marker 3 is marker 0 again (RBAC/RBAC-1)
    D, A = model_pair_statistics(pos)
    assert np.isnan(D[0, 3]) and np.isnan(A[0, 3]) and np.isnan(D[3, 0])
    assert D[0, 0] == 0.0 and np.isfinite(D[1, 3])
    tpl = train_subject("P", ["a", "b", "c", "a2"], pos, 120.0)
    LabelerModel(rate=120.0, subjects=[tpl])
    in_body = {i for b in tpl.bodies for i in b}
    assert 0 in in_body and 3 not in in_body  # the second name is a split track: no body


def test_a_split_track_gets_no_body_and_its_original_keeps_its_own(rng):
    """A second track of one physical marker (a CMU take's ``RBAC-1``: 4 mm from ``RBAC`` in
    the 8 frames it exists) would enter bodies as a rigid marker and, at a boot, take its
    original's point; training gives it no body. Two real markers 6 mm apart keep theirs."""
    from labeler_service.labeling.training import DUPLICATE_MM, split_tracks, train_subject

    pos = _markers_with_a_swinging_hand(rng, frames=60)[:, :3]
    dup = np.full_like(pos[:, :1], np.nan)
    dup[20:28] = pos[20:28, :1] + np.array([3.0, 2.5, 0.0])  # 3.9 mm off marker 0, 8 frames
    near = pos[:, 1:2] + np.array([0.0, 0.0, DUPLICATE_MM + 1.0])  # a real neighbour of 1
    pos = np.concatenate([pos, dup, near], axis=1)
    tpl = train_subject("P", ["a", "b", "c", "a-1", "b2"], pos, 120.0)
    in_body = {i for b in tpl.bodies for i in b}
    assert 3 not in in_body and {0, 1, 2, 4} <= in_body, tpl.bodies
    D = np.array(tpl.D_array())
    assert split_tracks(D, np.array([60, 60, 60, 8, 60])) == {3: 0}
