"""The rigid-body prediction kernels (``kernels/motion.py``) against their plain-numpy twins."""

from __future__ import annotations

import numpy as np
import pytest
import reference as ref

from labeler_service.labeling.kernels.motion import _body_motion, _body_predict
from labeler_service.labeling.kernels.state import MAX_BODY, new_bodies, new_tracks

BODIES = [[0, 1, 2, 3], [2, 3, 4], [4, 5, 6, 7, 8], [7, 8, 9]]  # overlapping, 10 markers


def _rotation(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _state(m=10):
    tracks = new_tracks(np.full(m, 1e6), np.ones(m, dtype=bool), [range(5), range(5, m)])
    d0 = [np.ones((len(b), len(b))) for b in BODIES]
    return tracks, new_bodies(m, BODIES, d0, d0, 8)


def _work():
    return np.zeros((MAX_BODY, 3)), np.zeros((MAX_BODY, 3)), np.zeros((3, 3)), np.zeros(3)


@pytest.mark.parametrize("tau", [0.0, 60.0])
def test_body_motion_matches_twin(rng, tau):
    _, bodies = _state()
    base = rng.normal(0, 100, (10, 3))
    for _frame in range(5):
        obs = base + rng.normal(0, 30, (10, 3))  # tau 60: some bodies move as one, some not
        obs[rng.random(10) < 0.25] = np.nan  # hidden markers
        kx = obs + rng.normal(0, 5, (10, 3))
        bodies.pred[:] = np.where(rng.random((4, MAX_BODY, 1)) < 0.2, np.nan, 1.0)
        bodies.pred[:, :, :] += rng.normal(0, 10, bodies.pred.shape)
        before = (bodies.mpos.copy(), bodies.pred.copy(), bodies.err.copy(), bodies.kerr.copy())
        want = ref.body_motion(BODIES, before[0], obs, before[1], kx, *before[2:], 5.0, tau)
        _body_motion(bodies, obs, kx, 0.02, 5.0, tau, *_work())
        for b, (R, t, moving, e_b, e_k, mpos) in enumerate(want):
            k = len(BODIES[b])
            assert bodies.moving[b] == moving
            if moving:
                np.testing.assert_allclose(bodies.R[b], R, atol=1e-9)
                np.testing.assert_allclose(bodies.t[b], t, atol=1e-7)
                assert bodies.motion_dt[b] == 0.02
            np.testing.assert_allclose(bodies.err[b, :k], e_b, rtol=1e-12)
            np.testing.assert_allclose(bodies.kerr[b, :k], e_k, rtol=1e-12)
            np.testing.assert_array_equal(bodies.mpos[b, :k], mpos)


def test_body_predict_matches_twin(rng):
    tracks, bodies = _state()
    bodies.moving[:] = [True, True, False, True]
    bodies.motion_dt[:] = [0.02, 0.03, 0.02, 0.021]  # body 1: another interval, unused
    for b in range(4):
        bodies.R[b] = _rotation(rng)
        bodies.t[b] = rng.normal(0, 50, 3)
    bodies.err[:] = rng.uniform(1, 100, bodies.err.shape)
    bodies.kerr[:] = rng.uniform(1, 100, bodies.kerr.shape)
    bodies.err[0, 1] = np.nan  # no record
    bodies.err[3, 0] = bodies.err[2, 3]  # a tie between bodies
    tracks.x[:] = rng.normal(0, 100, (10, 6))
    tracks.pos[:] = rng.normal(0, 100, (10, 3)).astype(np.float32)
    tracks.pos[6] = np.nan  # neither observed nor recovered: no rigid prediction
    want = ref.body_predict(
        BODIES,
        bodies.R,
        bodies.t,
        bodies.moving,
        bodies.motion_dt,
        bodies.err,
        bodies.kerr,
        tracks.x,
        tracks.pos.astype(np.float64),
        0.02,
    )
    kalman = tracks.x[:, :3].copy()
    _body_predict(tracks, bodies, 0.02)
    np.testing.assert_allclose(tracks.x, want, rtol=1e-9, atol=1e-6)
    np.testing.assert_array_equal(tracks.kx, kalman)  # the Kalman prediction is kept
    assert not np.allclose(want[:, :3], kalman)  # some markers did take a rigid prediction
    assert np.allclose(want[6], tracks.x[6])


def test_body_predict_follows_a_turning_body_exactly(rng):
    """A body turning about a fixed axis at a constant rate: the rigid prediction is exact,
    where a per-marker constant velocity misses by the arc's sagitta."""
    tracks, bodies = _state()
    Rstep = _rotation(rng)
    axis_point = np.array([300.0, -200.0, 900.0])
    prev = rng.normal(0, 60, (10, 3)) + 1000.0

    def move(p):
        return (p - axis_point) @ Rstep.T + axis_point

    bodies.pred[:] = np.nan
    _body_motion(bodies, prev, prev, 0.02, 5.0, 1.0, *_work())
    now = move(prev)
    _body_motion(bodies, now, now, 0.02, 5.0, 1.0, *_work())  # rigid: within 1 mm
    assert bodies.moving.all()
    tracks.pos[:] = now.astype(np.float32)
    # a record that says each body beats the Kalman filter
    bodies.err[:] = 1.0
    bodies.kerr[:] = 2.0
    tracks.x[:, :3] = 2 * now - prev  # constant velocity
    _body_predict(tracks, bodies, 0.02)
    nxt = move(now)
    np.testing.assert_allclose(tracks.x[:, :3], nxt, atol=1e-3)  # float32 positions
    assert np.abs(2 * now - prev - nxt).max() > 10.0  # the sagitta the rigid motion saves
