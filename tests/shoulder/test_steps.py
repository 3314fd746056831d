"""Steps 3-5 on controlled inputs: joint centres, skeleton structure, marker choice, weights."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from offline.shoulder.joints import best_chain, is_chain, joint_centre, skeleton_structure
from offline.shoulder.markers import distance_energy, select_markers
from offline.shoulder.rigid import apply, fill_transforms, fit_rigid, fit_rotation_about
from offline.shoulder.skinning import merge_small_segments, skin_weights
from offline.shoulder.synthesis import fit_weights_nnls, half_rotation, skin


def _two_bones(rng, n=300, joint=(100.0, 20.0, 50.0)):
    """Parent moves rigidly; child rotates about ``joint`` (rest space) relative to it."""
    j = np.asarray(joint)
    Rp = Rotation.from_rotvec(rng.normal(scale=0.3, size=(n, 3))).as_matrix()
    tp = rng.normal(scale=50.0, size=(n, 3))
    Rrel = Rotation.from_rotvec(rng.normal(scale=0.8, size=(n, 3))).as_matrix()
    Rc = Rp @ Rrel
    tc = np.einsum("fij,fj->fi", Rp, j - np.einsum("fij,j->fi", Rrel, j)) + tp
    return Rp, tp, Rc, tc, j


def test_joint_centre_recovers_a_ball_joint(rng):
    Rp, tp, Rc, tc, j = _two_bones(rng)
    est, rms = joint_centre(Rp, tp, Rc, tc, x0=j + 80.0)
    np.testing.assert_allclose(est, j, atol=0.05)
    assert rms < 0.1
    tc_noisy = tc + rng.normal(scale=2.0, size=tc.shape)
    Rc_nan = Rc.copy()
    Rc_nan[::10] = np.nan  # undetermined frames are skipped
    est, rms = joint_centre(Rp, tp, Rc_nan, tc_noisy, x0=j + 80.0)
    assert np.linalg.norm(est - j) < 3.0
    assert 1.0 < rms < 5.0


def test_chain_and_tree_structures():
    chainy = np.array([[0, 5, 50, 60], [5, 0, 4, 50], [50, 4, 0, 6], [60, 50, 6, 0]], float)
    order, parent = skeleton_structure(chainy, root=0)
    assert order == [0, 1, 2, 3] and is_chain(parent)
    assert best_chain(chainy, 0)[1] == pytest.approx(15.0)
    # segment 3 only fits as a side branch of 0: the tree attaches it there
    star = np.array([[0, 5, 50, 4], [5, 0, 4, 90], [50, 4, 0, 90], [4, 90, 90, 0]], float)
    order, parent = skeleton_structure(star, root=0, structure="tree")
    assert not is_chain(parent) and parent[3] == 0 and parent[1] == 0 and parent[2] == 1
    order, parent = skeleton_structure(star, root=0, structure="chain")
    assert is_chain(parent) and order[0] == 0
    with pytest.raises(ValueError, match="structure"):
        skeleton_structure(star, 0, structure="star")


def test_distance_energy_eq3():
    p = np.array([[0.0, 0, 0], [10, 0, 0], [100, 0, 0]])
    chosen = np.array([[0.0, 0, 0], [20, 0, 0]])
    np.testing.assert_allclose(distance_energy(p, chosen, 40.0), [1 + 0.5, 0.75 + 0.75, 0.0])


def test_select_markers_first_by_rigidity_then_spread():
    rest = np.array(
        [[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [100, 0, 0], [0, 100, 0], [50, 50, 0], [0, 0, 100]]
    )
    e_r = np.array([0.0, 0.01, 0.02, 0.5, 0.6, 0.9, 10.0])
    every = np.arange(7)
    chosen = select_markers(rest, every, every, e_r, n_select=4)
    # lowest e_r first; then markers 1 and 2 lose to spread-out ones (they sit on marker 0)
    np.testing.assert_array_equal(chosen, [0, 3, 4, 5])
    # with omega = 1 only rigidity counts
    np.testing.assert_array_equal(select_markers(rest, every, every, e_r, 3, omega=1.0), [0, 1, 2])
    with pytest.raises(ValueError, match="omega"):
        select_markers(rest, every, every, e_r, omega=2.0)


def test_rigid_fits_with_missing_samples(rng):
    src = rng.normal(scale=40.0, size=(6, 3))
    R = Rotation.random(20, random_state=4).as_matrix()
    t = rng.normal(scale=100.0, size=(20, 3))
    dst = apply(R, t, src)
    dst[3, :4] = np.nan  # only 2 visible: undetermined
    dst[5, 0] = np.nan
    Rf, tf = fit_rigid(src, dst)
    assert np.isnan(Rf[3]).all()
    ok = np.ones(20, bool)
    ok[3] = False
    np.testing.assert_allclose(Rf[ok], R[ok], atol=1e-9)
    Rf, tf = fill_transforms(Rf, tf)
    np.testing.assert_allclose(Rf[3], R[2], atol=1e-9)
    pivot = src[0]
    Ra, ta = fit_rotation_about(pivot, apply(R, t, pivot[None])[:, 0], src, apply(R, t, src))
    np.testing.assert_allclose(Ra, R, atol=1e-9)
    np.testing.assert_allclose(ta, t, atol=1e-6)


def test_skin_weights_recover_a_linear_blend(rng):
    n = 400
    RA = np.repeat(np.eye(3)[None], n, axis=0)
    tA = np.zeros((n, 3))
    RB = Rotation.from_rotvec(np.outer(np.sin(np.linspace(0, 9, n)), [0, 0, 1.2])).as_matrix()
    tB = rng.normal(scale=5.0, size=(n, 3))
    rest = rng.normal(scale=50.0, size=(5, 3))
    w_true = np.array([[1, 0], [0, 1], [0.7, 0.3], [0.4, 0.6], [0.5, 0.5]])
    R = np.stack([RA, RB], 1)
    t = np.stack([tA, tB], 1)
    pos = skin(rest, w_true, R, t) + rng.normal(scale=0.5, size=(n, 5, 3))
    from offline.shoulder.skinning import rigid_residuals

    e = rigid_residuals(pos, rest, R, t)
    labels = np.array([0, 1, 0, 1, 0])
    cand = [np.array([0]), np.array([1])] + [np.array([0, 1])] * 3
    W, sigma2 = skin_weights(labels, e, cand, 2, core=[np.array([0]), np.array([1])])
    np.testing.assert_allclose(W, w_true, atol=0.05)
    assert 0.1 < sigma2 < 2.0


def test_merge_small_segments_moves_markers_to_the_best_fit(rng):
    rest = rng.normal(scale=40.0, size=(9, 3))
    n = 50
    R = Rotation.from_rotvec(rng.normal(scale=0.5, size=(n, 3))).as_matrix()
    pos = np.empty((n, 9, 3))
    pos[:, :5] = apply(np.repeat(np.eye(3)[None], n, 0), np.zeros((n, 3)), rest[:5])
    pos[:, 5:] = apply(R, np.zeros((n, 3)), rest[5:])
    labels = np.array([0, 0, 0, 0, 2, 1, 1, 1, 1])  # marker 4 alone in segment 2
    new, merged = merge_small_segments(pos, rest, labels, 3, min_markers=4)
    assert merged == 1
    np.testing.assert_array_equal(new, [0, 0, 0, 0, 0, 1, 1, 1, 1])


def test_mg03_half_rotation_and_nnls_weights(rng):
    n = 60
    RA = Rotation.from_rotvec(rng.normal(scale=0.2, size=(n, 3))).as_matrix()
    rel = Rotation.from_rotvec(np.outer(np.linspace(-1, 1, n), [0, 1.0, 0])).as_matrix()
    half = half_rotation(RA, RA @ rel)
    np.testing.assert_allclose(half @ half.transpose(0, 2, 1), np.eye(3)[None].repeat(n, 0),
                               atol=1e-12)  # fmt: skip
    # relative to the parent: half the angle about the same axis (y), as a rotation vector
    np.testing.assert_allclose(
        Rotation.from_matrix(np.einsum("fji,fjk->fik", RA, half)).as_rotvec(),
        np.outer(np.linspace(-1, 1, n) / 2, [0, 1.0, 0]),
        atol=1e-9,
    )
    # and in the world frame (a relative rotation applied on the wrong side differs here)
    np.testing.assert_allclose(half, RA @ Rotation.from_rotvec(
        np.outer(np.linspace(-1, 1, n) / 2, [0, 1.0, 0])).as_matrix(), atol=1e-9)  # fmt: skip
    R = np.stack([RA, RA @ rel], 1)
    t = rng.normal(scale=3.0, size=(n, 2, 3))
    rest = rng.normal(scale=60.0, size=(4, 3))
    w_true = np.array([[1, 0], [0, 1], [0.25, 0.75], [0.6, 0.4]])
    pos = skin(rest, w_true, R, t)
    W = fit_weights_nnls(pos, rest, R, t, step=1)
    np.testing.assert_allclose(W, w_true, atol=1e-3)


@pytest.mark.parametrize("k", [9, 10])
def test_best_chain_beyond_the_exhaustive_range_is_still_the_minimum(k):
    """Past 8 segments the chain comes from a dynamic programme: the same minimum as every
    order (a hostile run's --k 20 tried 19! orders and never ended)."""
    from itertools import permutations

    from offline.shoulder.joints import _chain_cost, best_chain

    rng = np.random.default_rng(k)
    cost = rng.uniform(1.0, 50.0, (k, k))
    cost = (cost + cost.T) / 2
    order, total = best_chain(cost, 2)
    brute = min(_chain_cost(cost, [2, *p]) for p in permutations([s for s in range(k) if s != 2]))
    assert order[0] == 2 and sorted(order) == list(range(k))
    assert total == pytest.approx(brute) and total == pytest.approx(_chain_cost(cost, order))


def test_best_chain_of_many_segments_ends_with_a_valid_chain():
    from offline.shoulder.joints import _chain_cost, best_chain

    rng = np.random.default_rng(0)
    cost = rng.uniform(1.0, 50.0, (40, 40))
    cost = (cost + cost.T) / 2
    order, total = best_chain(cost, 5)
    assert order[0] == 5 and sorted(order) == list(range(40))
    assert total == pytest.approx(_chain_cost(cost, order))
    greedy = [5]  # no worse than the plain cheapest-next-link chain it starts from
    while len(greedy) < 40:
        greedy.append(
            min((s for s in range(40) if s not in greedy), key=lambda s: cost[greedy[-1], s])
        )
    assert total <= _chain_cost(cost, greedy) + 1e-9
