"""Every numba kernel of the labeler against its plain-numpy twin in ``tests/reference.py``."""

from __future__ import annotations

import numpy as np
import pytest
import reference as ref
from scipy.spatial.transform import Rotation

from labeler_service.labeling.config import LabelerConfig
from labeler_service.labeling.frame import MISSING, OBSERVED
from labeler_service.labeling.kernels.fitting import _fit_bodies, _search_body
from labeler_service.labeling.kernels.gating import _common_mode, _gate, _median_inplace, _regate
from labeler_service.labeling.kernels.kalman import _predict, _update
from labeler_service.labeling.kernels.params import DISPLACEMENT, KABSCH, kernel_params
from labeler_service.labeling.kernels.rigid import (
    COV0,
    _contest,
    _cov_add,
    _exchange,
    _horn_closed,
    _horn_jacobi,
    _kabsch,
    _keep_tracks,
    _max_residual,
    _recover,
    _robust_kabsch,
    _snapshot,
    _verify,
)
from labeler_service.labeling.kernels.spatial import _index
from labeler_service.labeling.kernels.state import (
    UNDECIDED,
    new_bodies,
    new_kabsch_scratch,
    new_recovery,
    new_scratch,
    new_tracks,
)
from labeler_service.labeling.kernels.window import _window_update


def _tracks(x, prev_state, n_reject=None):
    """Tracks of ``len(x)`` active markers (one subject) holding ``x``, the previous frame's
    ``state`` and ``n_reject`` (the arrays themselves: the kernels change them in place)."""
    m = x.shape[0]
    tr = new_tracks(np.full(m, 1e6), np.ones(m, dtype=bool), [range(m)])
    tr = tr._replace(x=x, state=prev_state)
    return tr if n_reject is None else tr._replace(n_reject=n_reject)


def _recovery(members, size, refs, ok):
    rc = new_recovery(members.shape[0])
    rc.members[:] = members
    rc.size[:] = size
    rc.ref[:] = refs
    rc.ok[:] = ok
    return rc


def _scratch(m, n_points, K=3, n_bodies=1, **arrays):
    """Scratch for ``m`` markers whose ``arrays`` (``assigned``, ``owner``, ...) are the
    caller's own (changed in place)."""
    return new_scratch(m, n_bodies, 1, K, n_points)._replace(**arrays)


# --------------------------------------------------------------------------- Kalman
@pytest.mark.parametrize("dt", [1 / 360, 1 / 120, 1 / 30, 0.25])
def test_factorised_kalman_equals_full_filter(rng, dt):
    m = 5
    x = rng.normal(0, 100, (m, 6))
    a = rng.uniform(0.5, 4, m)
    c = rng.uniform(10, 1e4, m)
    b = rng.uniform(-0.9, 0.9, m) * np.sqrt(a * c)
    P = np.stack([a, b, c], axis=1)
    q = rng.uniform(1e3, 1e6, m)
    z = x[:, :3] + rng.normal(0, 5, (m, 3))
    xs = [x[i].copy() for i in range(m)]
    P6 = [ref.p2_to_p6(P[i]) for i in range(m)]
    active = np.ones(m, dtype=bool)
    _predict(x, P, q, active, dt, 1e12)
    _update(x, P, z, active, 1.5, 1e6)
    for i in range(m):
        xr, Pr = ref.kalman_full_predict(xs[i], P6[i], q[i], dt)
        xr, Pr = ref.kalman_full_update(xr, Pr, z[i], 1.5)
        np.testing.assert_allclose(x[i], xr, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(ref.p2_to_p6(P[i]), Pr, rtol=1e-9, atol=1e-9)


def test_predict_caps_variance_and_skips_inactive(rng):
    x = rng.normal(0, 10, (3, 6))
    x0 = x.copy()
    P = np.tile([1e4, 10.0, 1e6], (3, 1))
    active = np.array([True, False, True])
    _predict(x, P, np.full(3, 1e6), active, 0.1, 100.0)
    assert np.all(P[active, 0] <= 100.0 + 1e-9)
    np.testing.assert_array_equal(x[1], x0[1])
    # the capped covariance stays positive semi-definite
    assert np.all(P[active, 1] ** 2 <= P[active, 0] * P[active, 2] + 1e-9)


# --------------------------------------------------------------------------- gating
def _run_gate(pred, s, active, points, g, K):
    m = pred.shape[0]
    cand = np.zeros((m, K), dtype=np.int32)
    cand_d2 = np.zeros((m, K))
    ncand = np.zeros(m, dtype=np.int32)
    _gate(pred, s, active, points, _index(points), g, K, cand, cand_d2, ncand)
    return cand, cand_d2, ncand


@pytest.mark.parametrize("K", [1, 2, 4])
def test_gate_matches_scipy_mahalanobis(rng, K):
    pred = rng.normal(0, 50, (12, 6))
    s = rng.uniform(20, 400, 12)
    points = rng.normal(0, 50, (30, 3)).astype(np.float32)
    points[3] = np.nan  # a NaN point never becomes a candidate
    pred[5, :3] = np.nan  # nor is a marker without a state gated
    active = rng.random(12) < 0.8
    cand, cand_d2, ncand = _run_gate(pred, s, active, points, 9.0, K)
    expected = ref.gate(pred, s, active, points, 9.0, K)
    for i, (js, ds) in enumerate(expected):
        assert ncand[i] == len(js)
        assert list(cand[i, : ncand[i]]) == js
        np.testing.assert_allclose(cand_d2[i, : ncand[i]], ds, rtol=1e-5)


def test_gate_degenerate_inputs():
    pred = np.zeros((2, 6))
    none = np.zeros((0, 3), dtype=np.float32)
    _, _, ncand = _run_gate(pred, np.ones(2), np.ones(2, bool), none, 16.0, 3)
    assert ncand.tolist() == [0, 0]
    same = np.zeros((4, 3), dtype=np.float32)  # four identical points: ties by index
    cand, d2, ncand = _run_gate(pred, np.ones(2), np.ones(2, bool), same, 16.0, 3)
    assert ncand.tolist() == [3, 3] and cand[0].tolist() == [0, 1, 2]
    assert np.all(d2 == 0)


def test_regate_only_free_points_within_radius(rng):
    x = rng.normal(0, 100, (6, 6))
    points = rng.normal(0, 100, (40, 3)).astype(np.float32)
    owner = np.where(rng.random(40) < 0.3, 1, -1).astype(np.int32)
    lost = np.array([True, False, True, True, False, True])
    K = 3
    cand = np.full((6, K), -7, dtype=np.int32)
    cand_d2 = np.zeros((6, K))
    ncand = np.full(6, 9, dtype=np.int32)
    radius = rng.uniform(60.0, 200.0, 6)
    _regate(x, lost, points, _index(points), owner, radius, 16.0, K, cand, cand_d2, ncand)
    expected = ref.regate(x, lost, points, owner, radius, 16.0, K)
    for i, js in expected.items():
        assert list(cand[i, : ncand[i]]) == js
    assert ncand[1] == 9 and ncand[4] == 9  # untouched


def test_common_mode_matches_twin(rng):
    groups = [np.arange(0, 8), np.arange(8, 14)]
    truth = rng.normal(0, 300, (14, 3))
    shift = np.array([[40.0, -25.0, 5.0], [-10.0, 0.0, 30.0]])
    x = np.zeros((14, 6))
    x[:8, :3] = truth[:8] - shift[0]
    x[8:, :3] = truth[8:] - shift[1]
    points = (truth + rng.normal(0, 0.5, truth.shape)).astype(np.float32)
    active = np.ones(14, dtype=bool)
    xr, sr = ref.common_mode(x, active, groups, points, 120.0, 2)
    subj_ptr = np.array([0, 8, 14])
    subj_idx = np.arange(14)
    out = np.zeros((2, 3))
    _common_mode(
        x, active, subj_ptr, subj_idx, points, _index(points), 120.0, 2, np.zeros((3, 14)), out
    )
    np.testing.assert_allclose(x, xr, atol=1e-6)
    np.testing.assert_allclose(out, sr, atol=1e-6)
    np.testing.assert_allclose(out, shift, atol=1.5)  # and it finds the jump


def test_median_in_place_is_np_median():
    """The common mode's in-place median is ``np.median``'s value, bit for bit (odd and even
    counts, ties, sorted and reversed input)."""
    rng = np.random.default_rng(3)
    for n in list(range(1, 40)) + [51, 64, 101]:
        for kind in range(4):
            v = rng.normal(0, 30, n)
            if kind == 1:
                v = v.round()  # ties
            elif kind == 2:
                v = np.sort(v)
            elif kind == 3:
                v = np.sort(v)[::-1].copy()
            buf = np.concatenate([v, rng.normal(0, 1, 5)])  # entries past n are not read
            assert _median_inplace(buf, n) == np.median(v)
            assert sorted(buf[:n]) == sorted(v)  # reordered only


@pytest.mark.parametrize("seed", range(6))
def test_common_mode_crowd_matches_full_scan(seed):
    """A crowd: subjects packed within the radius of each other, ghost points, markers whose
    nearest point lies beyond the first narrow search or beyond the radius, inactive and NaN
    markers; the bounded searches choose the full scan's points, so the shifts are its own."""
    rng = np.random.default_rng(seed)
    n_subj, per = 5, 12
    m = n_subj * per
    truth = rng.normal(0, 60, (m, 3)) + np.repeat(rng.normal(0, 150, (n_subj, 3)), per, axis=0)
    jump = rng.normal(0, 45, (n_subj, 3))  # some nearest points beyond the first 40 mm
    x = np.zeros((m, 6))
    x[:, :3] = truth - np.repeat(jump, per, axis=0) + rng.normal(0, 8, (m, 3))
    x[3, :3] += 500.0  # nothing within the radius
    x[7, 0] = np.nan
    ghosts = rng.normal(0, 200, (40, 3))
    points = np.vstack([truth + rng.normal(0, 1, truth.shape), ghosts]).astype(np.float32)
    points = points[rng.permutation(len(points))]
    active = rng.random(m) > 0.1
    groups = [np.arange(k * per, (k + 1) * per) for k in range(n_subj)]
    xr, sr = ref.common_mode(x, active, groups, points, 120.0, 3)
    out = np.zeros((n_subj, 3))
    subj_ptr = np.arange(0, m + 1, per)
    _common_mode(
        x, active, subj_ptr, np.arange(m), points, _index(points), 120.0, 3, np.zeros((3, m)), out
    )
    np.testing.assert_allclose(x, xr, atol=1e-9, equal_nan=True)
    np.testing.assert_allclose(out, sr, atol=1e-9)


# --------------------------------------------------------------------------- Eq. 5 search
def _random_body(rng, n, K, n_points=12, miss_prob=0.2):
    points = rng.normal(0, 80, (n_points, 3)).astype(np.float32)
    true_pts = rng.choice(n_points, n, replace=False)
    Db = np.zeros((8, 8))
    Ab = np.full((8, 8), np.nan)
    for i in range(n):
        for j in range(n):
            if i != j:
                Db[i, j] = np.linalg.norm(points[true_pts[i]] - points[true_pts[j]]) + rng.normal(
                    0, 2
                )
                Ab[i, j] = rng.uniform(0.5, 4)
    Db = (Db + Db.T) / 2
    Ab = np.where(np.isnan(Ab), np.nan, (Ab + Ab.T) / 2)
    if n > 2:
        Db[0, 1] = Db[1, 0] = np.nan  # an unknown link
    opts = np.full((8, K + 1), -1, dtype=np.int64)
    nopts = np.zeros(8, dtype=np.int64)
    mot = np.zeros((8, K + 1))
    for k in range(n):
        cands = list(rng.choice(n_points, rng.integers(0, K + 1), replace=False))
        if rng.random() > miss_prob and true_pts[k] not in cands:
            cands = [int(true_pts[k])] + cands[: K - 1]
        for o, c in enumerate(cands):
            opts[k, o] = c
            mot[k, o] = np.exp(-0.5 * rng.uniform(0, 9))
        mot[k, len(cands)] = np.exp(-0.5 * 16)
        nopts[k] = len(cands) + 1
    return points, Db, Ab, opts, nopts, mot


@pytest.mark.parametrize("n", [1, 2, 3, 5, 6])
def test_branch_and_bound_equals_itertools_product(rng, n):
    for _ in range(25):
        points, Db, Ab, opts, nopts, mot = _random_body(rng, n, 3)
        perm = rng.permutation(8).astype(np.int64)
        perm[:n] = rng.permutation(n)
        choice = np.zeros(8, dtype=np.int64)
        partial = np.zeros(18)
        best_choice = np.zeros(8, dtype=np.int64)
        args = (n, perm, opts, nopts, mot, Db, Ab, 2.0, 0.02, np.exp(-4.5), 0.25, points)
        s = _search_body(*args, choice, partial, best_choice)
        sr, arg = ref.search_body(*args)
        assert s == pytest.approx(sr, abs=1e-9)
        chosen = [int(opts[k, best_choice[k]]) for k in range(n)]
        np.testing.assert_allclose(
            ref.score(chosen, perm, [mot[k, best_choice[k]] for k in range(n)], *args[5:]),
            sr,
            atol=1e-9,
        )


def test_search_prefers_observed_consistent_points_over_missing():
    # three markers on a rigid triangle, a ghost far off the shape
    points = np.array([[0, 0, 0], [100, 0, 0], [0, 100, 0], [40, 40, 40]], dtype=np.float32)
    Db = np.zeros((8, 8))
    Ab = np.ones((8, 8))
    tri = points[:3].astype(float)
    for i in range(3):
        for j in range(3):
            Db[i, j] = np.linalg.norm(tri[i] - tri[j])
    opts = np.full((8, 3), -1, dtype=np.int64)
    opts[0, :2] = [0, 3]
    opts[1, :2] = [1, 3]
    opts[2, :1] = [3]  # the true point of marker 2 is absent: only the ghost is a candidate
    nopts = np.array([3, 3, 2, 0, 0, 0, 0, 0])
    mot = np.full((8, 3), 0.5)
    perm = np.arange(8)
    best = np.zeros(8, dtype=np.int64)
    args = (3, perm, opts, nopts, mot, Db, Ab, 2.0, 0.0, np.exp(-4.5), 0.25, points)
    _search_body(*args, np.zeros(8, dtype=np.int64), np.zeros(18), best)
    assert [int(opts[k, best[k]]) for k in range(3)] == [0, 1, -1]


def _random_scene(rng, nb=5, m=14, n_points=18, K=3):
    body_markers = np.full((nb, 8), -1, dtype=np.int32)
    body_size = np.zeros(nb, dtype=np.int32)
    for b in range(nb):
        k = int(rng.integers(2, 5))
        body_markers[b, :k] = rng.choice(m, k, replace=False)
        body_size[b] = k
    points = rng.normal(0, 100, (n_points, 3)).astype(np.float32)
    truth = rng.choice(n_points, m, replace=False) if n_points >= m else None
    Db = np.full((nb, 8, 8), np.nan)
    Ab = np.full((nb, 8, 8), np.nan)
    for b in range(nb):
        for i in range(body_size[b]):
            for j in range(body_size[b]):
                pi, pj = truth[body_markers[b, i]], truth[body_markers[b, j]]
                Db[b, i, j] = np.linalg.norm(points[pi] - points[pj])
                Ab[b, i, j] = 1.5
    cand = np.zeros((m, K), dtype=np.int32)
    cand_d2 = np.zeros((m, K))
    ncand = np.zeros(m, dtype=np.int32)
    for i in range(m):
        cs = list(rng.choice(n_points, K, replace=False))
        if truth[i] not in cs and rng.random() < 0.8:
            cs[0] = truth[i]
        c = int(rng.integers(0, K + 1))
        cand[i, :c] = cs[:c]
        cand_d2[i, :c] = np.sort(rng.uniform(0, 10, c))
        ncand[i] = c
    mb = [[b for b in range(nb) if i in body_markers[b, : body_size[b]]] for i in range(m)]
    mb_ptr = np.cumsum([0] + [len(x) for x in mb]).astype(np.int64)
    mb_idx = np.array([b for x in mb for b in x] or [0], dtype=np.int32)
    return body_markers, body_size, Db, Ab, cand, cand_d2, ncand, points, mb_ptr, mb_idx


def _fit(scene, K=3):
    body_markers, body_size, Db, Ab, cand, cand_d2, ncand, points, mb_ptr, mb_idx = scene
    m, nb, n = cand.shape[0], body_markers.shape[0], points.shape[0]
    members = [list(body_markers[b, : body_size[b]]) for b in range(nb)]
    k = body_size
    D0 = [Db[b, : k[b], : k[b]] for b in range(nb)]
    A0 = [Ab[b, : k[b], : k[b]] for b in range(nb)]
    bodies = new_bodies(m, members, D0, A0, 2)
    np.testing.assert_array_equal(bodies.D, Db)  # NaN outside each body, as in the scene
    # the builder's marker -> bodies index is the scene's
    np.testing.assert_array_equal(bodies.mb_ptr, mb_ptr)
    np.testing.assert_array_equal(bodies.mb_idx[: mb_ptr[-1]], mb_idx[: mb_ptr[-1]])
    assigned = np.full(m, UNDECIDED, dtype=np.int32)
    owner = np.full(n, -1, dtype=np.int32)
    scratch = _scratch(
        m, n, K, nb, cand=cand, cand_d2=cand_d2, ncand=ncand, assigned=assigned, owner=owner
    )
    params = kernel_params(
        LabelerConfig(a_floor_mm=2.0, a_relative=0.02, motion_weight=0.25, gate_chi2=16.0, K=K)
    )
    _fit_bodies(bodies, points, np.exp(-4.5), scratch, params)
    return assigned, owner


def test_algorithm1_equals_literal_recompute_everything(rng):
    for _ in range(20):
        scene = _random_scene(rng)
        assigned, owner = _fit(scene)
        body_markers, body_size, Db, Ab, cand, cand_d2, ncand, points, _, _ = scene
        a_ref, o_ref = ref.fit_bodies(
            body_markers,
            body_size,
            Db,
            Ab,
            cand,
            cand_d2,
            ncand,
            points,
            2.0,
            0.02,
            np.exp(-4.5),
            0.25,
            16.0,
        )
        in_body = np.zeros(cand.shape[0], bool)
        for b in range(body_markers.shape[0]):
            in_body[body_markers[b, : body_size[b]]] = True
        np.testing.assert_array_equal(assigned[in_body], a_ref[in_body])
        np.testing.assert_array_equal(owner, o_ref)
        # a point is never given to two markers
        used = assigned[assigned >= 0]
        assert used.size == np.unique(used).size


# --------------------------------------------------------------------------- Eq. 1-2
def test_window_matches_twin_with_missing_samples(rng):
    nb, T, m = 2, 7, 6
    members = [[0, 1, 2], [2, 3, 4, 5]]
    D0 = [np.full((len(b), len(b)), 11.0) for b in members]
    A0 = [np.full((len(b), len(b)), 3.0) for b in members]
    bodies = new_bodies(m, members, D0, A0, T)
    body_markers, body_size, D, A = bodies.members, bodies.size, bodies.D, bodies.A
    hist = []
    for f in range(20):
        obs = rng.normal(0, 100, (m, 3))
        obs[rng.random(m) < 0.25] = np.nan
        hist.append(obs)
        _window_update(bodies, obs, f % T, 3)
        for b in range(nb):
            k = body_size[b]
            for i in range(k):
                for j in range(i + 1, k):
                    mi, mj = body_markers[b, i], body_markers[b, j]
                    h = [np.linalg.norm(o[mi] - o[mj]) for o in hist[-T:]]
                    h = np.asarray(h, dtype=np.float32)
                    dr, ar = ref.window_stats(h, 3, 11.0, 3.0)
                    assert D[b, i, j] == pytest.approx(dr, rel=1e-6)
                    assert A[b, i, j] == pytest.approx(ar, rel=1e-4, abs=1e-3)
                    assert D[b, j, i] == D[b, i, j]


# --------------------------------------------------------------------------- recovery
def _rot(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_kabsch_matches_twin_and_recovers_rotation(rng):
    src = rng.normal(0, 100, (6, 3))
    R0 = _rot(rng)
    dst = src @ R0.T + np.array([10.0, -5.0, 3.0])
    R = np.zeros((3, 3))
    t = np.zeros(3)
    _kabsch(src, dst, 6, R, t)
    Rr, tr = ref.kabsch(src, dst)
    np.testing.assert_allclose(R, Rr, atol=1e-9)
    np.testing.assert_allclose(t, tr, atol=1e-7)
    np.testing.assert_allclose(R, R0, atol=1e-9)
    # degenerate: three collinear points still give a proper rotation (det +1)
    line = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]])
    _kabsch(line, line + 1.0, 3, R, t)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_kabsch_equals_svd_twin_on_hard_cases(rng):
    """Horn's quaternion solution is the SVD solution: noisy sets, half-turns, 3-point sets,
    and mirrored targets (where the best proper rotation is not a reflection)."""
    R = np.zeros((3, 3))
    t = np.zeros(3)
    for case in range(60):
        n = 3 + case % 5
        src = rng.normal(0, 100, (n, 3))
        R0 = _rot(rng)
        if case % 6 == 1:  # a half-turn: the quaternion's scalar part is ~0
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            R0 = 2.0 * np.outer(axis, axis) - np.eye(3)
        dst = src @ R0.T + rng.normal(0, 50, 3) + rng.normal(0, 2.0, (n, 3))
        if case % 6 == 2:
            dst[:, 0] *= -1.0  # mirrored
        _kabsch(src, dst, n, R, t)
        Rr, tr = ref.kabsch(src, dst)
        cost = np.sum((src @ R.T + t - dst) ** 2)
        cost_r = np.sum((src @ Rr.T + tr - dst) ** 2)
        assert np.linalg.det(R) == pytest.approx(1.0)
        assert cost == pytest.approx(cost_r, rel=1e-9, abs=1e-6)
        if case % 6 != 2:  # a unique optimum: the same rotation
            np.testing.assert_allclose(R, Rr, atol=1e-7)


def _cov(src, dst):
    """The centred cross-covariance 9-tuple of :func:`_kabsch`."""
    cov = COV0
    for a, b in zip(src - src.mean(0), dst - dst.mean(0), strict=True):
        cov = _cov_add(cov, *a, *b)
    return cov


def _quat_rot(q):
    return Rotation.from_quat(np.asarray(q), scalar_first=True).as_matrix()


def test_horn_closed_form_is_jacobis_rotation_or_declines(rng):
    """The closed form (Newton root + adjugate) gives Jacobi's rotation on well-conditioned
    sets - full 3D, planar (triangles), noisy, half-turns, mirrored - and declines (NaN, so
    ``_kabsch`` falls back to Jacobi) on collinear and single-point sets."""
    used = 0
    for case in range(400):
        n = 3 + case % 6
        src = rng.normal(0, 100, (n, 3))
        if case % 4 == 1:
            src[:, 2] = 0.0  # planar
        R0 = _rot(rng)
        if case % 8 == 3:  # a half-turn
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            R0 = 2.0 * np.outer(axis, axis) - np.eye(3)
        dst = src @ R0.T + rng.normal(0, 300, 3) + rng.normal(0, [0.0, 1.0, 20.0][case % 3], (n, 3))
        if case % 8 == 5:
            dst[:, 0] *= -1.0  # mirrored
        cov = _cov(src, dst)
        q = _horn_closed(cov)
        if np.isnan(q[0]):
            continue
        used += 1
        assert np.linalg.norm(q) == pytest.approx(1.0)
        np.testing.assert_allclose(_quat_rot(q), _quat_rot(_horn_jacobi(cov)), atol=1e-9)
    assert used >= 390  # declining is for ill-conditioned sets only
    line = np.outer(np.arange(4.0), [1.0, 2.0, 3.0])
    assert np.isnan(_horn_closed(_cov(line, line @ _rot(rng).T))[0])
    one = np.ones((3, 3))
    assert np.isnan(_horn_closed(_cov(one, one))[0])
    # nearly collinear: declined, or agrees with Jacobi
    thin = line + rng.normal(0, 1e-4, line.shape)
    cov = _cov(thin, thin @ _rot(rng).T)
    q = _horn_closed(cov)
    if not np.isnan(q[0]):
        np.testing.assert_allclose(_quat_rot(q), _quat_rot(_horn_jacobi(cov)), atol=1e-9)


@pytest.mark.parametrize("scale", [1e-30, 1e-12, 1.0, 1e12, 1e24])
def test_kabsch_holds_at_any_scale(rng, scale):
    """The closed form's cofactors grow as the cube of the spread: unscaled, a 1e25 mm body gave
    a zero matrix and a 1e-27 mm one a division by zero (a review)."""
    src = rng.normal(0, 100, (6, 3)) * scale
    R0 = _rot(rng)
    R = np.zeros((3, 3))
    t = np.zeros(3)
    _kabsch(src, src @ R0.T, 6, R, t)
    np.testing.assert_allclose(R, R0, atol=1e-9)


def test_robust_kabsch_drops_outlier(rng):
    src = rng.normal(0, 100, (6, 3))
    R0 = _rot(rng)
    dst = src @ R0.T
    dst[2] += 40.0  # a neighbour across a joint that moved
    R = np.zeros((3, 3))
    t = np.zeros(3)
    kept = _robust_kabsch(src.copy(), dst.copy(), 6, R, t, 5.0)
    Rr, tr, kept_r = ref.robust_kabsch(src, dst, 5.0)
    assert kept == kept_r == 5
    np.testing.assert_allclose(R, R0, atol=1e-8)
    np.testing.assert_allclose(R, Rr, atol=1e-8)


@pytest.mark.parametrize("method", ["kabsch", "displacement"])
def test_recover_matches_twin(rng, method):
    m = 7
    members = np.full((m, 8), -1, dtype=np.int64)
    size = np.zeros(m, dtype=np.int64)
    refs = np.zeros((m, 8, 3))
    ok = np.ones(m, dtype=bool)
    shape = rng.normal(0, 80, (m, 3))
    for i in range(m):
        mem = [i] + [j for j in range(m) if j != i][:5]
        members[i, : len(mem)] = mem
        size[i] = len(mem)
        refs[i, : len(mem)] = shape[mem]
    R0 = _rot(rng)
    obs = shape @ R0.T + 50.0
    missing = np.zeros(m, dtype=bool)
    missing[[1, 4]] = True
    obs[[1, 4]] = np.nan
    obs[6] = np.nan  # not missing, just unseen: fewer neighbours
    rec = np.full((m, 3), np.nan)
    has = np.zeros(m, dtype=np.int64)
    code = KABSCH if method == "kabsch" else DISPLACEMENT
    rc = _recovery(members, size, refs, ok)
    _recover(missing, rc, obs, code, rec, has, new_kabsch_scratch(), 5.0)
    assert (has > 0).tolist() == missing.tolist()
    assert has[1] == 4 and has[4] == 4  # neighbours used (6 is unseen)
    for i in (1, 4):
        expected = ref.recover(i, list(members[i, : size[i]]), refs[i], obs, method, 5.0)
        np.testing.assert_allclose(rec[i], expected, atol=1e-7)
    if method == "kabsch":  # exact for a rigid motion
        np.testing.assert_allclose(rec[[1, 4]], shape[[1, 4]] @ R0.T + 50.0, atol=1e-7)


def test_a_member_never_seen_leaves_a_partial_snapshot_the_fit_skips(rng):
    """A recovery set with a member hidden for good still gives its marker a snapshot (the
    marker and 3+ members); a full one replaces it and is never replaced by a partial one."""
    m, age_min = 6, 10
    shape = rng.normal(0, 80, (m, 3))
    members = np.full((m, 8), -1, dtype=np.int64)
    members[:, :m] = [[i] + [j for j in range(m) if j != i] for i in range(m)]
    size = np.full(m, m, dtype=np.int64)
    rc = _recovery(members, size, np.zeros((m, 8, 3)), np.zeros(m, dtype=bool))
    age = np.full(m, age_min, dtype=np.int64)
    age[5] = 0  # never observed
    obs = shape.copy()
    obs[5] = np.nan
    _snapshot(age, age_min, obs, rc)
    assert rc.ok[:5].all() and not rc.ok[5]  # 5 itself has no snapshot to be estimated from
    row = members[0, :m].tolist().index(5)
    assert np.isnan(rc.ref[0, row]).all()
    np.testing.assert_allclose(rc.ref[0, 0], shape[0])
    # marker 0 hidden, 5 seen now: the fit uses 1-4 only and is exact for a rigid motion
    R0 = _rot(rng)
    now = shape @ R0.T + 30.0
    obs_now = now.copy()
    obs_now[0] = np.nan
    rec = np.full((m, 3), np.nan)
    has = np.zeros(m, dtype=np.int64)
    missing = np.zeros(m, dtype=bool)
    missing[0] = True
    _recover(missing, rc, obs_now, KABSCH, rec, has, new_kabsch_scratch(), 5.0)
    assert has[0] == 4
    np.testing.assert_allclose(rec[0], now[0], atol=1e-7)
    # too few members seen: no partial snapshot (the marker and 3 members are needed)
    rc2 = _recovery(members, size, np.zeros((m, 8, 3)), np.zeros(m, dtype=bool))
    age2 = np.array([age_min, age_min, age_min, 0, 0, 0])
    _snapshot(age2, age_min, obs, rc2)
    assert not rc2.ok[0]
    # a full snapshot replaces the partial one and stays when a member is hidden again
    age[5] = age_min
    _snapshot(age, age_min, now, rc)
    np.testing.assert_allclose(rc.ref[0, :m], now[members[0, :m]])
    moved = now + 100.0
    age[5] = 0
    _snapshot(age, age_min, moved, rc)
    np.testing.assert_allclose(rc.ref[0, :m], now[members[0, :m]])


# --------------------------------------------------------------------------- track continuity
def _contest_scene(rng, m=12):
    """Markers on a rigid cloud; recovery sets of 5; all observed at their true points."""
    shape = rng.normal(0, 80, (m, 3))
    members = np.full((m, 8), -1, dtype=np.int64)
    size = np.zeros(m, dtype=np.int64)
    refs = np.zeros((m, 8, 3))
    for i in range(m):
        order = np.argsort(np.linalg.norm(shape - shape[i], axis=1))[:5]
        members[i, :5] = order  # itself first (distance 0)
        size[i] = 5
        refs[i, :5] = shape[order]
    R0 = _rot(rng)
    pos = shape @ R0.T + 30.0
    x = np.zeros((m, 6))
    x[:, :3] = pos + rng.normal(0, 1.0, (m, 3))
    return pos, members, size, refs, x


S_FLOOR = 30.0**2 / 16.27  # innovation variance at the 30 mm gate floor


def _frame(points) -> np.ndarray:
    """A frame's points as they reach the kernels: float32, as decoded from the wire (a float64
    frame compiled twins of ``_contest``, ``_verify`` and ``_exchange`` only the tests ran)."""
    return np.ascontiguousarray(points, dtype=np.float32)


def _observed(points, assigned) -> np.ndarray:
    """Each marker's observed point, NaN for none (float64, as the scratch holds them)."""
    obs = np.where((assigned >= 0)[:, None], points[np.maximum(assigned, 0)], np.nan)
    return obs.astype(np.float64)


CHECKS = kernel_params(LabelerConfig(gate_chi2=16.27, jump_mm=8.0, verify_mm=8.0))


def _run_contest(assigned, owner, prev, x, points, obs, sets, s=None):
    """``_contest`` on the caller's arrays (changed in place); ``sets`` = ``(members, size,
    refs, ok)``; ``jump_mm`` = ``verify_mm`` = 8 mm, ``robust_fit_mm`` = 5 mm (the defaults)."""
    m = assigned.shape[0]
    s = np.full(m, S_FLOOR) if s is None else s
    scratch = _scratch(m, points.shape[0], assigned=assigned, owner=owner, obs=obs, s=s)
    return _contest(points, _tracks(x, prev), _recovery(*sets), scratch, CHECKS)


def test_contest_returns_a_point_to_its_tracked_marker(rng):
    pos, members, size, refs, x = _contest_scene(rng)
    m = pos.shape[0]
    points = _frame(pos)
    assigned = np.arange(m, dtype=np.int32)
    # marker 3 (tracked) lost its point to marker 7, which jumped 25 mm for it; 7's own point is
    # hidden in this frame (point 7 is a leftover nobody holds)
    x[7, :3] = pos[3] + np.array([25.0, 0.0, 0.0])
    assigned[3] = -1
    assigned[7] = 3
    owner = np.full(m, -1, dtype=np.int32)
    for i in range(m):
        if assigned[i] >= 0:
            owner[assigned[i]] = i
    owner[7] = -1
    prev = np.ones(m, dtype=np.uint8)
    obs = _observed(points, assigned)
    ok = np.ones(m, dtype=bool)
    state = (assigned.copy(), owner.copy(), obs.copy())
    n = _run_contest(assigned, owner, prev, x, points, obs, (members, size, refs, ok))
    assert n == 1
    assert assigned[3] == 3 and owner[3] == 3 and assigned[7] == -1
    assert np.isnan(obs[7]).all()
    np.testing.assert_allclose(obs[3], points[3])
    # marker 3 hidden before (not tracked): it still predicts the point 16 times better in
    # Mahalanobis terms, so it takes it back
    a2, o2, ob2 = (v.copy() for v in state)
    prev[3] = 2
    assert _run_contest(a2, o2, prev, x, points, ob2, (members, size, refs, ok)) == 1
    assert a2[3] == 3 and a2[7] == -1
    # ... but not when it predicts the point 15 mm off (not a quarter of 25 mm, squared) ...
    a3, o3, ob3 = (v.copy() for v in state)
    x3 = x.copy()
    x3[3, :3] = pos[3] + np.array([0.0, 0.0, 15.0])
    assert _run_contest(a3, o3, prev, x3, points, ob3, (members, size, refs, ok)) == 0
    np.testing.assert_array_equal(a3, state[0])
    # ... unless the holder's own prediction is sharper (its 25 mm jump is then implausible)
    s = np.full(m, S_FLOOR)
    s[7] = 0.25 * S_FLOOR
    assert _run_contest(a3, o3, prev, x3, points, ob3, (members, size, refs, ok), s) == 1
    assert a3[3] == 3


def test_contest_hands_back_along_a_chain(rng):
    """Algorithm 1 gave marker 2 (its own point hidden) the point of marker 8, 20 mm off, and
    marker 8 the point of marker 10 (holdout03 `occlude2`: the clavicle set, 20 mm apart). When
    the contest reached marker 2, marker 8 still held a point, so only marker 10 took its own
    back, and marker 8 stayed missing beside its point for 35 frames: the contest runs again
    while it changes something."""
    pos, members, size, refs, x = _contest_scene(rng)
    m = pos.shape[0]
    points = _frame(pos)
    x[:, :3] = pos  # every tracked marker predicts its own point
    x[2, :3] = pos[8] + np.array([20.0, 0.0, 0.0])  # marker 2's own point is hidden
    assigned = np.arange(m, dtype=np.int32)
    assigned[2] = 8  # 20 mm from marker 2's prediction
    assigned[8] = 10  # marker 8 took marker 10's point, far from its own prediction
    assigned[10] = -1
    owner = np.full(m, -1, dtype=np.int32)
    for i in range(m):
        if assigned[i] >= 0:
            owner[assigned[i]] = i
    obs = _observed(points, assigned)
    prev = np.ones(m, dtype=np.uint8)
    ok = np.zeros(m, dtype=bool)  # no rigid veto either way
    n = _run_contest(assigned, owner, prev, x, points, obs, (members, size, refs, ok))
    assert n == 2
    assert assigned[10] == 10 and assigned[8] == 8 and assigned[2] == -1
    assert owner[8] == 8 and owner[10] == 10


def test_contest_tracked_taker_needs_a_sharp_prediction(rng):
    pos, members, size, refs, x = _contest_scene(rng)
    m = pos.shape[0]
    points = _frame(pos)
    assigned = np.arange(m, dtype=np.int32)
    owner = np.arange(m, dtype=np.int32)
    # marker 6 jumped 40 mm onto point 6; marker 9 (tracked, missing) predicts it 10 mm off:
    # a quarter of the holder's Mahalanobis distance, but beyond jump_mm for a tracked marker
    x[6, :3] = pos[6] + np.array([40.0, 0.0, 0.0])
    x[9, :3] = pos[6] + np.array([0.0, 10.0, 0.0])
    assigned[9] = -1
    owner[9] = -1
    obs = _observed(points, assigned)
    prev = np.ones(m, dtype=np.uint8)
    ok = np.zeros(m, dtype=bool)  # no rigid veto either way
    assert _run_contest(assigned, owner, prev, x, points, obs, (members, size, refs, ok)) == 0
    prev[9] = 2  # the same prediction from a marker that was hidden: it takes the point
    assert _run_contest(assigned, owner, prev, x, points, obs, (members, size, refs, ok)) == 1
    assert assigned[9] == 6 and assigned[6] == -1


def test_contest_keeps_a_point_the_holders_body_supports(rng):
    pos, members, size, refs, x = _contest_scene(rng)
    m = pos.shape[0]
    points = _frame(pos)
    assigned = np.arange(m, dtype=np.int32)
    owner = np.arange(m, dtype=np.int32)
    # marker 5 jumped 20 mm (its prediction was off) but sits exactly where its neighbours say;
    # marker 2 lost its point and predicts marker 5's point closely: 5 keeps it
    x[5, :3] = pos[5] + np.array([0.0, 20.0, 0.0])
    x[2, :3] = pos[5] + 1.0
    assigned[2] = -1
    owner[2] = -1
    obs = _observed(points, assigned)
    prev = np.ones(m, dtype=np.uint8)
    ok = np.ones(m, dtype=bool)
    n = _run_contest(assigned, owner, prev, x, points, obs, (members, size, refs, ok))
    assert n == 0
    assert assigned[5] == 5 and assigned[2] == -1


def test_contest_matches_twin(rng):
    moved = 0
    for trial in range(40):
        pos, members, size, refs, x = _contest_scene(rng, m=14)
        m = pos.shape[0]
        points = _frame(pos + rng.normal(0, 2.0, pos.shape))
        # random assignment: a permutation with a few markers missing
        perm = rng.permutation(m).astype(np.int32)
        assigned = np.where(rng.random(m) < 0.6, np.arange(m), perm).astype(np.int32)
        _, first = np.unique(assigned, return_index=True)
        keep = np.zeros(m, dtype=bool)
        keep[first] = True
        assigned[~keep | (rng.random(m) < 0.25)] = -1
        owner = np.full(m, -1, dtype=np.int32)
        owner[assigned[assigned >= 0]] = np.flatnonzero(assigned >= 0)
        # predictions: some sharp, some off by up to 40 mm
        x[:, :3] = pos + rng.normal(0, 1.0, (m, 3)) * rng.choice([1.0, 15.0], size=(m, 1))
        prev = rng.choice(np.array([0, 1, 2], dtype=np.uint8), size=m, p=[0.1, 0.7, 0.2])
        ok = rng.random(m) < 0.8
        obs = _observed(points, assigned)
        s = S_FLOOR * rng.choice([1.0, 1.0, 4.0], size=m)  # some markers hidden for a while
        a_r, o_r, ob_r = assigned.copy(), owner.copy(), obs.copy()
        n = _run_contest(assigned, owner, prev, x, points, obs, (members, size, refs, ok), s)
        mem = [list(members[i, : size[i]]) for i in range(m)]
        n_r = ref.contest(
            a_r,
            o_r,
            np.ones(m, dtype=bool),
            prev,
            x,
            s,
            16.27,
            points,
            ob_r,
            mem,
            refs,
            ok,
            8.0,
            8.0,
            5.0,
        )
        assert n == n_r, trial
        moved += n
        np.testing.assert_array_equal(assigned, a_r)
        np.testing.assert_array_equal(owner, o_r)
        np.testing.assert_allclose(obs, ob_r, atol=1e-9)
    assert moved > 0  # the random frames do exercise hand-overs


# --------------------------------------------------------------------------- 3D check
def _run_verify(assigned, owner, prev, x, points, obs, members, size, refs, n_reject, limit):
    """``_verify`` on the caller's arrays (changed in place), every marker a single candidate:
    the default distances (verify 8, near 12, reject 25, jump 8, robust fit 5 mm), no suspect
    points, no round robin, swaps allowed."""
    m = assigned.shape[0]
    ncand = np.ones(m, dtype=np.int32)
    scratch = _scratch(m, points.shape[0], assigned=assigned, owner=owner, obs=obs, ncand=ncand)
    rc = _recovery(members, size, refs, np.ones(m, dtype=bool))
    params = kernel_params(LabelerConfig(suspect_mm=0.0, verify_every=0, reject_limit=limit))
    tracks = _tracks(x, prev, n_reject)
    return _verify(points, _index(points), 0, tracks, rc, scratch, params)


@pytest.mark.parametrize(
    ("leap_mm", "prev", "used", "refused"),
    [
        (40.0, 2, 0, True),  # re-acquisition 40 mm off its estimate: refused
        (40.0, 2, 5, True),  # the sixth refusal in a row
        (40.0, 2, 6, False),  # the refusals in a row are used up: accepted (no lock-out)
        (15.0, 2, 0, False),  # re-acquisition 15 mm off: only a closer free point would win
        (40.0, 1, 0, False),  # tracked through the previous frame: kept
    ],
)
def test_verify_refuses_a_reacquisition_off_the_rigid_estimate(rng, leap_mm, prev, used, refused):
    pos, members, size, refs, x = _contest_scene(rng)
    m = pos.shape[0]
    # marker 4's own point is hidden; a ghost sits leap_mm from where it is predicted
    x[4, :3] = pos[4]
    ghost = pos[4] + leap_mm * np.array([0.0, 0.6, 0.8])
    points = _frame(np.vstack([np.delete(pos, 4, axis=0), ghost[None]]))
    assigned = np.array([i if i < 4 else i - 1 for i in range(m)], dtype=np.int32)
    assigned[4] = m - 1
    owner = np.full(m, -1, dtype=np.int32)
    owner[assigned] = np.arange(m)
    obs = points[assigned].astype(np.float64)
    prev_state = np.ones(m, dtype=np.uint8)
    prev_state[4] = prev
    n_reject = np.zeros(m, dtype=np.int64)
    n_reject[4] = used
    _run_verify(assigned, owner, prev_state, x, points, obs, members, size, refs, n_reject, 6)
    assert (assigned[4] == -1) == refused
    assert n_reject[4] == used + int(refused)
    others = np.delete(np.arange(m), 4)
    np.testing.assert_array_equal(assigned[others], [i if i < 4 else i - 1 for i in others])


def test_max_residual_matches_twin_and_flags_a_moved_pair(rng):
    src = rng.normal(0, 100, (4, 3))
    R0 = _rot(rng)
    dst = src @ R0.T + 20.0
    R = np.zeros((3, 3))
    t = np.zeros(3)
    _kabsch(src, dst, 4, R, t)
    assert _max_residual(src, dst, 4, R, t) < 1e-6
    # two of four neighbours moved together (a joint bent): no rigid fit of all four, and the
    # robust fit can drop only one of them
    dst[2:] += np.array([0.0, 40.0, 0.0])
    kept = _robust_kabsch(src.copy(), dst.copy(), 4, R, t, 5.0)
    assert kept == 3
    s2, d2 = src.copy(), dst.copy()
    _robust_kabsch(s2, d2, 4, R, t, 5.0)
    res = _max_residual(s2, d2, kept, R, t)
    assert res > 5.0
    assert res == pytest.approx(ref.max_residual(s2[:kept], d2[:kept], R, t), abs=1e-9)


# --------------------------------------------------------------------------- exchange


def _exchange_scene(apex_offset):
    """A triangle body {0, 1, 2} (a pelvis: 0 and 1 are the hips 215 mm apart, 2 behind them
    ``apex_offset`` mm off the midline) and a fourth marker in no body; every marker tracked in
    the previous frame and predicted 40 mm off its point. Returns ``(points, x, bodies)``."""
    points = _frame(
        [[108.0, 0.0, 0.0], [-107.0, 0.0, 0.0], [apex_offset, -250.0, 0.0], [0.0, 500.0, 0.0]]
    )
    x = np.zeros((4, 6))
    x[:, :3] = points + np.array([30.0, 25.0, 10.0])  # 40.3 mm off, as a 25 Hz pelvis
    d = np.linalg.norm(points[:3, None] - points[None, :3], axis=2)
    bodies = new_bodies(4, [[0, 1, 2]], [d], [np.full((3, 3), 3.0)], 2)
    return points, x, bodies


def _run_exchange(points, x, bodies, assigned, prev=None, **config):
    m = x.shape[0]
    owner = np.full(points.shape[0], -1, dtype=np.int32)
    owner[assigned[assigned >= 0]] = np.flatnonzero(assigned >= 0)
    prev = np.ones(m, dtype=np.uint8) if prev is None else prev
    scratch = _scratch(m, points.shape[0], assigned=assigned, owner=owner)
    params = kernel_params(LabelerConfig(**config))
    n = _exchange(points, _tracks(x, prev), bodies, scratch, params)
    return n, owner


def test_exchange_undoes_a_symmetric_pair_the_predictions_refute():
    points, x, bodies = _exchange_scene(apex_offset=0.5)
    assigned = np.array([1, 0, 2, 3], dtype=np.int32)  # the hips on each other's points
    n, owner = _run_exchange(points, x, bodies, assigned)
    assert n == 1
    np.testing.assert_array_equal(assigned, [0, 1, 2, 3])
    np.testing.assert_array_equal(owner, [0, 1, 2, 3])
    # a right reading stays as it is
    assert _run_exchange(points, x, bodies, assigned)[0] == 0
    np.testing.assert_array_equal(assigned, [0, 1, 2, 3])


def test_exchange_leaves_what_shape_or_tracking_does_not_support():
    # the hips on their own points, but predicted on each other's (a fast turn): with the apex
    # 60 mm off the midline the exchanged hips would break their links to it by ~46 mm, worse
    # than Eq. 5's missing marker - the shape refutes the exchange, the reading stays
    points, x, bodies = _exchange_scene(apex_offset=60.0)
    x[[0, 1]] = x[[1, 0]]
    assigned = np.array([0, 1, 2, 3], dtype=np.int32)
    assert _run_exchange(points, x, bodies, assigned)[0] == 0
    np.testing.assert_array_equal(assigned, [0, 1, 2, 3])
    # on the near-symmetric body the shape cannot tell, and the predictions decide
    points, x, bodies = _exchange_scene(apex_offset=0.5)
    x[[0, 1]] = x[[1, 0]]
    assert _run_exchange(points, x, bodies, assigned.copy())[0] == 1
    points, x, bodies = _exchange_scene(apex_offset=0.5)
    wrong = np.array([1, 0, 2, 3], dtype=np.int32)
    # a marker not tracked in the previous frame has no prediction to trust
    prev = np.array([1, 2, 1, 1], dtype=np.uint8)
    assert _run_exchange(points, x, bodies, wrong.copy(), prev)[0] == 0
    # predictions that favour the exchange by less than the ratio asked (0.18 here)
    assert _run_exchange(points, x, bodies, wrong.copy(), exchange_ratio=0.1)[0] == 0
    assert _run_exchange(points, x, bodies, wrong.copy(), exchange_ratio=0.2)[0] == 1
    # markers in no shared body are never exchanged: marker 0 holds marker 3's point and the
    # other way round, each predicted 5 mm from its own point (only the body rule stops it)
    a = np.array([3, 1, 2, 0], dtype=np.int32)
    x[0, :3] = points[0] + 5.0
    x[3, :3] = points[3] + 5.0
    assert _run_exchange(points, x, bodies, a)[0] == 0
    np.testing.assert_array_equal(a, [3, 1, 2, 0])
    # a NaN prediction never exchanges
    x = _exchange_scene(apex_offset=0.5)[1]
    x[0, :3] = np.nan
    assert _run_exchange(points, x, bodies, wrong.copy())[0] == 0


def test_exchange_equals_its_twin_on_random_scenes(rng):
    """``_exchange`` against ``reference.exchange`` (marker by marker, plain Python): random
    overlapping bodies, some of them near-symmetric, points exchanged in pairs and chains,
    predictions near the truth or near another marker's point, some markers not tracked."""
    cfg = LabelerConfig()
    params = kernel_params(cfg)
    exchanged = 0
    for _ in range(150):
        m = int(rng.integers(4, 10))
        truth = rng.normal(0, 120.0, (m, 3))
        if rng.random() < 0.5:  # a near-symmetric pair about marker 2
            truth[1] = truth[0] * np.array([-1.0, 1.0, 1.0])
            truth[2] = np.array([0.0, 0.0, truth[0, 2] - 200.0])
        nb = int(rng.integers(1, 4))
        bodies = [sorted(rng.choice(m, int(rng.integers(2, min(m, 6) + 1)), replace=False).tolist())
                  for _ in range(nb)]  # fmt: skip
        D = [np.linalg.norm(truth[b][:, None] - truth[b][None], axis=2) for b in bodies]
        A = [np.full((len(b), len(b)), float(rng.uniform(1.0, 6.0))) for b in bodies]
        points = _frame(truth + rng.normal(0, 2.0, truth.shape))
        assigned = np.arange(m, dtype=np.int32)
        for _ in range(int(rng.integers(0, 3))):  # exchanges and chains
            i, j = rng.choice(m, 2, replace=False)
            assigned[[i, j]] = assigned[[j, i]]
        assigned[rng.random(m) < 0.15] = -1
        owner = np.full(m, -1, dtype=np.int32)
        owner[assigned[assigned >= 0]] = np.flatnonzero(assigned >= 0)
        x = np.zeros((m, 6))
        x[:, :3] = truth + rng.normal(0, 8.0, truth.shape)
        far = rng.random(m) < 0.2
        x[far, :3] = points[rng.integers(0, m, int(far.sum()))]
        prev = np.where(rng.random(m) < 0.85, 1, 2).astype(np.uint8)
        want_a, want_o = assigned.copy(), owner.copy()
        n_ref = ref.exchange(want_a, want_o, np.ones(m, bool), prev, x, points, bodies, D, A,
                             cfg.a_floor_mm, cfg.a_relative, params.miss_term, cfg.jump_mm,
                             cfg.exchange_ratio)  # fmt: skip
        b = new_bodies(m, bodies, D, A, 2)
        scratch = _scratch(m, m, assigned=assigned, owner=owner)
        n = _exchange(points, _tracks(x, prev), b, scratch, params)
        assert n == n_ref
        np.testing.assert_array_equal(assigned, want_a)
        np.testing.assert_array_equal(owner, want_o)
        has = assigned >= 0
        np.testing.assert_array_equal(owner[assigned[has]], np.flatnonzero(has))
        exchanged += n > 0
    assert exchanged >= 10  # (the scenes do exercise the exchange)


# --------------------------------------------------------------------------- keep tracks
KT_DT = 1 / 100
GHOST = 12  # the extra point of _kt_scene


def _kt_scene(rng, m=12):
    """``m`` markers 60 mm apart on a line, tracked (age 50) last frame at ``pos`` and moving
    at 0.5 m/s; this frame's points are their continuations plus a ghost (point 12) 22 mm
    from marker 3's. Marker 7 (coasting) holds point 3, marker 3 the ghost."""
    pos = np.zeros((m, 3))
    pos[:, 0] = 60.0 * np.arange(m)
    pos[:, 1] = rng.normal(0, 5, m)
    v = np.array([500.0, 0.0, 0.0])
    x = np.zeros((m, 6))
    x[:, :3] = pos + v * KT_DT + 22.0 * np.array([0.0, 0.0, 1.0])  # predictions moved 22 mm
    x[:, 3:] = v
    points = np.vstack([pos + v * KT_DT, pos[3] + v * KT_DT + [0.0, 0.0, 22.0]])
    points = points.astype(np.float32)  # as a decoded frame reaches the kernels
    assigned = np.arange(m, dtype=np.int32)
    assigned[3], assigned[7] = GHOST, 3
    owner = np.full(points.shape[0], -1, dtype=np.int32)
    for i in range(m):
        owner[assigned[i]] = i
    owner[7] = -1  # point 7 left over
    prev = np.full(m, OBSERVED, dtype=np.uint8)
    prev[7] = MISSING
    age = np.full(m, 50, dtype=np.int64)
    age[7] = 0
    return pos, x, points, assigned, owner, prev, age


def _run_keep(pos, x, points, assigned, owner, prev, age, s=None, sets=None):
    """``_keep_tracks`` on the caller's arrays; ``sets``: recovery sets (default: none, so no
    rigid estimate vetoes)."""
    m = assigned.shape[0]
    if sets is None:
        sets = _recovery(
            np.full((m, 8), -1, dtype=np.int64), np.zeros(m, dtype=np.int64),
            np.zeros((m, 8, 3)), np.zeros(m, dtype=bool),
        )  # fmt: skip
    obs = np.where((assigned >= 0)[:, None], points[np.maximum(assigned, 0)], np.nan)
    s = np.full(m, S_FLOOR) if s is None else s
    scratch = _scratch(m, points.shape[0], assigned=assigned, owner=owner, obs=obs, s=s)
    tracks = _tracks(x, prev)._replace(pos=pos.astype(np.float32), age=age)
    n = _keep_tracks(points, _index(points), KT_DT, tracks, sets, scratch, CHECKS)
    return n, obs


def test_keep_tracks_a_coasting_marker_gives_a_tracked_continuation_back(rng):
    pos, x, points, assigned, owner, prev, age = _kt_scene(rng)
    n, obs = _run_keep(pos, x, points, assigned, owner, prev, age)
    assert n == 1
    assert assigned[3] == 3 and owner[3] == 3 and assigned[7] == -1
    assert owner[GHOST] == -1  # marker 3's ghost is free again
    np.testing.assert_allclose(obs[3], points[3])
    assert np.isnan(obs[7]).all()


def test_keep_tracks_a_young_track_gives_it_back_an_established_one_keeps_it(rng):
    pos, x, points, assigned, owner, prev, age = _kt_scene(rng)
    points[7] += 500.0  # marker 7's own point is elsewhere: only point 3 is in question
    prev[7] = OBSERVED
    age[7] = 2  # tracked 2 frames (on a ghost), now on marker 3's continuation
    assert _run_keep(pos, x, points, assigned, owner, prev, age)[0] == 1
    assert assigned[3] == 3 and assigned[7] == -1
    pos, x, points, assigned, owner, prev, age = _kt_scene(rng)
    points[7] += 500.0
    prev[7] = OBSERVED
    age[7] = 50  # tracked as long: the contest's and the exchange's case
    before = assigned.copy()
    assert _run_keep(pos, x, points, assigned, owner, prev, age)[0] == 0
    np.testing.assert_array_equal(assigned, before)


def test_keep_tracks_a_free_continuation_is_taken_back_from_a_ghost(rng):
    pos, x, points, assigned, owner, prev, age = _kt_scene(rng)
    assigned[7], owner[3], owner[7] = 7, -1, 7  # point 3 free, marker 7 on its own point
    prev[7], age[7] = OBSERVED, 50
    n, _ = _run_keep(pos, x, points, assigned, owner, prev, age)
    assert n == 1 and assigned[3] == 3 and owner[3] == 3 and owner[GHOST] == -1
    assert assigned[7] == 7


def test_keep_tracks_no_hand_back_when_the_continuation_is_not_unambiguous(rng):
    # a second point 12 mm from marker 3's continuation (within twice jump_mm)
    pos, x, points, assigned, owner, prev, age = _kt_scene(rng)
    extra = points[3] + [0.0, 12.0, 0.0]
    points = np.vstack([points, extra]).astype(np.float32)
    owner = np.append(owner, -1).astype(np.int32)
    before = assigned.copy()
    assert _run_keep(pos, x, points, assigned, owner, prev, age)[0] == 0
    np.testing.assert_array_equal(assigned, before)
    # 30 mm away it is no rival for a sharp track, but it is for a loose one (the berth is
    # twice the predicted deviation, 20 mm)
    pos, x, points, assigned, owner, prev, age = _kt_scene(rng)
    points = np.vstack([points, points[3] + [0.0, 30.0, 0.0]]).astype(np.float32)
    owner = np.append(owner, -1).astype(np.int32)
    a2, o2 = assigned.copy(), owner.copy()
    assert _run_keep(pos, x, points, a2, o2, prev, age)[0] == 1
    s = np.full(assigned.shape[0], S_FLOOR)
    s[3] = 20.0**2
    assert _run_keep(pos, x, points, assigned, owner, prev, age, s=s)[0] == 0


def test_keep_tracks_no_hand_back_when_the_track_does_not_continue_onto_the_point(rng):
    # the point lies 10 mm from marker 3's continuation (beyond jump_mm, 8 mm)
    pos, x, points, assigned, owner, prev, age = _kt_scene(rng)
    points[3] += [10.0, 0.0, 0.0]
    before = assigned.copy()
    assert _run_keep(pos, x, points, assigned, owner, prev, age)[0] == 0
    np.testing.assert_array_equal(assigned, before)


def test_keep_tracks_the_holders_rigid_estimate_vetoes(rng):
    """A marker back beside its body (its Kabsch estimate on the point) keeps the point against
    a track that took it meanwhile (a pile of performers: the tracked marker on another's
    point since a contact)."""
    pos, x, points, assigned, owner, prev, age = _kt_scene(rng)
    m = assigned.shape[0]
    members = np.full((m, 8), -1, dtype=np.int64)
    size = np.zeros(m, dtype=np.int64)
    refs = np.zeros((m, 8, 3))
    ok = np.zeros(m, dtype=bool)
    members[7, :4] = [7, 2, 4, 5]  # marker 7's body places it at point 3
    size[7] = 4
    refs[7, :4] = points[[3, 2, 4, 5]]
    ok[7] = True
    sets = _recovery(members, size, refs, ok)
    before = assigned.copy()
    assert _run_keep(pos, x, points, assigned, owner, prev, age, sets=sets)[0] == 0
    np.testing.assert_array_equal(assigned, before)
    # an estimate 20 mm off (beyond verify_mm) does not veto
    refs[7, 0] = points[3] + [0.0, 20.0, 0.0]
    sets = _recovery(members, size, refs, ok)
    assert _run_keep(pos, x, points, assigned, owner, prev, age, sets=sets)[0] == 1
    assert assigned[3] == 3 and assigned[7] == -1
