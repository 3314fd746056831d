"""Line 12 of Algorithm 1 in the distrust order: score times rigidity (kernels/fitting.py)."""

from __future__ import annotations

import numpy as np
import pytest
import reference as ref
from labeling.test_kernels import _random_scene, _scratch

from labeler_service.labeling.config import LabelerConfig
from labeler_service.labeling.kernels.fitting import _fit_bodies, _rigidity
from labeler_service.labeling.kernels.params import kernel_params
from labeler_service.labeling.kernels.state import UNDECIDED, new_bodies

TOL, W = 6.0, 0.02


def _params(**kw):
    base = dict(a_floor_mm=2.0, a_relative=0.02, motion_weight=0.25, gate_chi2=16.0)
    return kernel_params(LabelerConfig(**(base | kw)))


def test_rigidity_matches_twin(rng):
    nb = 30
    size = rng.integers(1, 9, nb).astype(np.int32)
    D = rng.uniform(20.0, 400.0, (nb, 8, 8))
    A = rng.exponential(4.0, (nb, 8, 8))
    A[rng.random((nb, 8, 8)) < 0.1] = np.nan  # links the window does not know
    for b in range(nb):
        got = _rigidity(b, size, D, A, TOL, W)
        assert got == pytest.approx(ref.rigidity(D[b], A[b], size[b], TOL, W), abs=1e-12)
        assert 0.0 < got <= 1.0


def test_rigidity_of_a_rigid_and_of_a_bending_body():
    size = np.array([3, 3], dtype=np.int32)
    D = np.full((2, 8, 8), 150.0)
    A = np.full((2, 8, 8), 1.0)  # cost 1 + 3 = 4 mm <= 6: as rigid as body formation asks
    A[1, 0, 2] = 47.0  # one link bends: cost 50 mm -> 6 / 50
    assert _rigidity(0, size, D, A, TOL, W) == 1.0
    assert _rigidity(1, size, D, A, TOL, W) == pytest.approx((1.0 + 1.0 + 6.0 / 50.0) / 3.0)


def _fit(scene, distrust, K=3):
    body_markers, body_size, Db, Ab, cand, cand_d2, ncand, points, _, _ = scene
    m, nb, n = cand.shape[0], body_markers.shape[0], points.shape[0]
    k = body_size
    members = [list(body_markers[b, : k[b]]) for b in range(nb)]
    D0 = [Db[b, : k[b], : k[b]] for b in range(nb)]
    A0 = [Ab[b, : k[b], : k[b]] for b in range(nb)]
    bodies = new_bodies(m, members, D0, A0, 2)
    assigned = np.full(m, UNDECIDED, dtype=np.int32)
    owner = np.full(n, -1, dtype=np.int32)
    scratch = _scratch(
        m, n, K, nb, cand=cand, cand_d2=cand_d2, ncand=ncand, assigned=assigned, owner=owner
    )
    _fit_bodies(bodies, points, np.exp(-4.5), scratch, _params(K=K), distrust)
    return assigned, owner


def test_distrust_order_equals_literal_algorithm1_with_weights(rng):
    changed = 0
    for _ in range(30):
        scene = _random_scene(rng)
        body_markers, body_size, Db, Ab, cand, cand_d2, ncand, points, _, _ = scene
        # window deviations from rigid to far beyond the formation tolerance (symmetric)
        a = rng.choice([1.5, 8.0, 40.0], Ab.shape)
        Ab[:] = np.minimum(a, a.transpose(0, 2, 1))
        assigned, owner = _fit(scene, True)
        weight = [ref.rigidity(Db[b], Ab[b], body_size[b], TOL, W) for b in range(len(body_size))]
        args = (body_markers, body_size, Db, Ab, cand, cand_d2, ncand, points)
        a_ref, o_ref = ref.fit_bodies(*args, 2.0, 0.02, np.exp(-4.5), 0.25, 16.0, weight)
        a_plain, _ = ref.fit_bodies(*args, 2.0, 0.02, np.exp(-4.5), 0.25, 16.0)
        in_body = np.zeros(cand.shape[0], bool)
        for b in range(body_markers.shape[0]):
            in_body[body_markers[b, : body_size[b]]] = True
        np.testing.assert_array_equal(assigned[in_body], a_ref[in_body])
        np.testing.assert_array_equal(owner, o_ref)
        changed += int(np.any(a_plain[in_body] != a_ref[in_body]))
    assert changed > 0  # the order matters on these scenes: the test sees the weights


def _bending_scene():
    """A rigid body R (markers 0, 1, 2) and a body S (markers 2, 3) whose one link the window
    shows bending (A = 40 mm). Marker 2 has two candidates: its true point p2 and q, where S's
    link fits exactly; R fits p2 only roughly (each link off by one deviation), so S scores
    higher and, in the paper's order, takes q for marker 2 first."""
    p = np.array(
        [
            [0.0, 0.0, 0.0],  # p0
            [120.0, 0.0, 0.0],  # p1
            [0.0, 120.0, 0.0],  # p2
            [0.0, 370.0, 0.0],  # p3: 250 mm from p2
            [0.0, 220.0, 0.0],  # q: 150 mm from p3
        ],
        dtype=np.float32,
    )
    body_markers = np.full((2, 8), -1, dtype=np.int32)
    body_markers[0, :3] = [0, 1, 2]
    body_markers[1, :2] = [2, 3]
    body_size = np.array([3, 2], dtype=np.int32)
    Db = np.full((2, 8, 8), np.nan)
    Ab = np.full((2, 8, 8), np.nan)
    truth = [0, 1, 2]
    for i in range(3):
        for j in range(3):
            d = float(np.linalg.norm(p[truth[i]] - p[truth[j]]))
            Db[0, i, j] = d + (2.4 if i != j else 0.0)  # one (floored) deviation off
            Ab[0, i, j] = 1.0
    Db[1, :2, :2] = [[0.0, 150.0], [150.0, 0.0]]
    Ab[1, :2, :2] = [[0.0, 40.0], [40.0, 0.0]]
    cand = np.array([[0, 0, 0], [1, 0, 0], [2, 4, 0], [3, 0, 0]], dtype=np.int32)
    ncand = np.array([1, 1, 2, 1], dtype=np.int32)
    cand_d2 = np.ones((4, 3))
    mb_ptr = np.array([0, 1, 2, 4, 5], dtype=np.int64)
    mb_idx = np.array([0, 0, 0, 1, 1], dtype=np.int32)
    return body_markers, body_size, Db, Ab, cand, cand_d2, ncand, p, mb_ptr, mb_idx


def test_a_bending_body_no_longer_pulls_a_rigid_bodys_marker():
    plain, _ = _fit(_bending_scene(), False)
    assert plain[2] == 4  # S won line 12 and gave marker 2 the point its bent link likes
    assigned, owner = _fit(_bending_scene(), True)
    np.testing.assert_array_equal(assigned[:4], [0, 1, 2, 3])  # R first: every marker right
    np.testing.assert_array_equal(owner, [0, 1, 2, 3, -1])
