"""The residual gate (``LabelerConfig.residual_gate``, kernels/step.py): a marker's gate is at
least ``residual_gate`` times its own recent RMS prediction residual, and the candidates it
admits keep the Kalman filter's metric (``_kalman_metric``)."""

from __future__ import annotations

import numpy as np
import pytest
from labeling.scene import articulated, frame_points

from labeler_service.labeling.config import LabelerConfig
from labeler_service.labeling.kernels.step import _kalman_metric
from labeler_service.labeling.labeler import Labeler

R = 4.0
S_MIN = 30.0**2 / 16.27


def _kalman_metric_twin(P, r, s_min, gone, s, cand_d2, ncand):
    s0 = np.maximum(P[:, 0] + r, s_min)
    s0[gone] = s_min
    out_s = s.copy()
    out_d2 = cand_d2.copy()
    wide = s > s0
    for i in np.flatnonzero(wide):
        out_d2[i, : ncand[i]] *= s[i] / s0[i]
        out_s[i] = s0[i]
    return out_s, out_d2


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_kalman_metric_matches_twin(seed):
    rng = np.random.default_rng(seed)
    m, k = 12, 4
    P = np.zeros((m, 3))
    P[:, 0] = rng.uniform(0.0, 400.0, m)
    gone = rng.random(m) < 0.2
    s0 = np.maximum(P[:, 0] + R, S_MIN)
    s0[gone] = S_MIN
    s = s0 * np.where(rng.random(m) < 0.5, rng.uniform(1.0, 30.0, m), 1.0)
    ncand = rng.integers(0, k + 1, m).astype(np.int32)
    cand_d2 = rng.uniform(0.0, 16.27, (m, k))
    want_s, want_d2 = _kalman_metric_twin(P, R, S_MIN, gone, s, cand_d2, ncand)
    got_s, got_d2 = s.copy(), cand_d2.copy()
    _kalman_metric(P, R, S_MIN, gone, got_s, got_d2, ncand)
    np.testing.assert_allclose(got_s, want_s)
    np.testing.assert_allclose(got_d2, want_d2)
    np.testing.assert_allclose(got_s, s0)  # every later stage reads the filter's own variance


def test_unwidened_markers_untouched():
    P = np.array([[100.0, 0.0, 0.0], [5.0, 0.0, 0.0]])
    s = np.array([104.0, S_MIN])  # exactly the filter's variances
    d2 = np.array([[1.0, 2.0], [3.0, 4.0]])
    ncand = np.array([2, 2], dtype=np.int32)
    _kalman_metric(P, R, S_MIN, np.zeros(2, dtype=bool), s, d2, ncand)
    np.testing.assert_array_equal(d2, [[1.0, 2.0], [3.0, 4.0]])


def _run(residual_gate: float, rate: float, step: int):
    rng = np.random.default_rng(3)
    pos, names = articulated(rng, subjects=2, frames=600, rate=120.0)
    pos = pos[::step]
    lab = Labeler(names, rate, LabelerConfig(residual_gate=residual_gate))
    init = 12
    for f in range(pos.shape[0]):
        pts, truth = frame_points(rng, pos[f])
        lab.process(pts, f / rate, truth if f < init else None)
    return lab


def test_residual_record_is_the_running_mean_of_tracked_errors():
    lab = _run(2.5, 120.0, 1)
    res = lab._tracks.res
    tracked = np.isfinite(res)
    assert tracked.all()  # every marker was tracked through consecutive frames
    # at 120 Hz the constant-velocity prediction misses by a few mm: RMS well under the floor
    assert np.sqrt(res).max() < 30.0


def test_off_keeps_no_influence_at_full_rate():
    """At a full rate the residuals stay under the 30 mm gate floor: the labels are those of
    the labeler without the residual gate."""
    a = _run(2.5, 120.0, 1)
    b = _run(0.0, 120.0, 1)
    np.testing.assert_array_equal(a._tracks.state, b._tracks.state)
    np.testing.assert_allclose(a._tracks.pos, b._tracks.pos)
