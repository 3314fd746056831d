"""Rigid-body prediction (ours, docs/algorithm.md "Rigid-body prediction").

The paper predicts every marker on its own with a constant-velocity Kalman filter (Eq. 3). A
forearm at 30-50 Hz turns by tens of degrees between frames; each of its markers then moves on
an arc, not a line, and the per-marker prediction lands where the proximal neighbour now is.
Here every rigid body also predicts its markers as one rigid motion:

1. **Pose motion.** After each frame, the body's inter-frame rigid motion ``(R, t)`` is the
   Kabsch fit (:func:`.rigid._kabsch`) of its members observed in the previous frame
   (``bodies.mpos``) onto the same members observed now (at least 3): the pose's linear and
   angular velocity over one frame (a constant twist: a rotation about any axis, so a forearm
   turning about the elbow is followed on its arc). With ``body_rigid_mm`` > 0 a body whose
   members that fit leaves more than that far apart predicts nothing (it is not moving as one).
2. **Prediction.** At the next frame the same motion is applied again to the members' reported
   positions (observed or recovered): ``pred = R pos + t``, when the frame interval matches
   the one the motion was measured over (within 25 %).
3. **Which prediction a marker takes.** Every body keeps, per member, the running mean squared
   error per axis of its own predictions (``bodies.err``) and of the member's Kalman prediction
   (``bodies.kerr``), over the frames the member was observed (exponential memory of
   ``body_error_frames`` frames that rises at once when an error jumps). A marker takes the
   prediction of the body that predicted it best, if that beat its Kalman filter: the data of
   each marker decides whether a rigid motion or the per-marker filter foresees it better.
   The Kalman state then holds that prediction (position, and the velocity of the predicted
   displacement), so the common-mode shift, the gate, the motion term of Eq. 5, track
   continuity and the 3D check all read one prediction; the filter's update (Eq. 4) follows
   from there, and a marker whose bodies predict nothing keeps its constant-velocity state.

The gate variance stays the Kalman filter's (``p_pp + r``, floored): sizing it from the
measured error instead widened the tennis serve's gate usefully at 50 Hz but let the 12.5 Hz
cells search far too wide (docs/algorithm.md).
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit
from labeler_service.labeling.kernels.rigid import _kabsch, _max_residual


@njit
def _keep_kalman(tracks):
    """``tracks.kx = tracks.x[:, :3]``: this frame's constant-velocity (Kalman) predictions,
    kept before the rigid-body ones replace them (and, without those, where a marker that loses
    its point starts following it, :mod:`.follow`)."""
    x, kx = tracks.x, tracks.kx
    for i in range(x.shape[0]):
        for a in range(3):
            kx[i, a] = x[i, a]


@njit
def _body_predict(tracks, bodies, dt):
    """The rigid-body predictions of this frame, in the Kalman states ``tracks.x``, in place.

    In: ``tracks.x`` after the constant-velocity prediction (Eq. 3), ``dt`` this frame's
    interval. Every body with a measured motion (``bodies.moving``) over a matching interval
    writes ``bodies.pred (B, 8, 3)`` (NaN rows for members with no reported position); the
    Kalman predictions are kept in ``tracks.kx``. A marker takes the prediction of its body with
    the lowest ``err`` below its ``kerr`` (module docstring, step 3).
    """
    x, pos = tracks.x, tracks.pos
    members, size = bodies.members, bodies.size
    R, t, pred, err, kerr = bodies.R, bodies.t, bodies.pred, bodies.err, bodies.kerr
    moving, motion_dt = bodies.moving, bodies.motion_dt
    _keep_kalman(tracks)
    for b in range(members.shape[0]):
        ok = moving[b] and abs(dt - motion_dt[b]) <= 0.25 * motion_dt[b]
        for k in range(size[b]):
            m = members[b, k]
            if not ok or pos[m, 0] != pos[m, 0]:  # noqa: PLR0124 (NaN test)
                for a in range(3):
                    pred[b, k, a] = np.nan
                continue
            p0, p1, p2 = np.float64(pos[m, 0]), np.float64(pos[m, 1]), np.float64(pos[m, 2])
            for a in range(3):
                pred[b, k, a] = R[b, a, 0] * p0 + R[b, a, 1] * p1 + R[b, a, 2] * p2 + t[b, a]
    mb_ptr, mb_idx = bodies.mb_ptr, bodies.mb_idx
    for m in range(x.shape[0]):
        best_b = -1
        best_k = -1
        for e in range(mb_ptr[m], mb_ptr[m + 1]):
            b = mb_idx[e]
            k = 0
            while members[b, k] != m:
                k += 1
            if not err[b, k] < kerr[b, k]:  # also no record (NaN)
                continue
            if best_b >= 0 and not err[b, k] < err[best_b, best_k]:
                continue
            if pred[b, k, 0] == pred[b, k, 0]:  # noqa: PLR0124 (NaN test)
                best_b = b
                best_k = k
        if best_b < 0:
            continue
        for a in range(3):
            # the Kalman state takes the rigid prediction (the gate and the later checks read
            # x): the predicted position, and the velocity of the predicted displacement
            x[m, a] = pred[best_b, best_k, a]
            x[m, 3 + a] = (pred[best_b, best_k, a] - pos[m, a]) / dt


@njit
def _body_motion(bodies, obs, kx, dt, memory, tau, src, dst, Rk, tk):
    """After the frame: the prediction errors and the next inter-frame motion of every body.

    ``obs (M, 3)``: this frame's observed positions (NaN otherwise); ``kx (M, 3)``: the Kalman
    predictions of this frame; ``memory``: frames of the error's exponential memory; ``tau``:
    ``body_rigid_mm`` (0 = no rigidity test); ``src``, ``dst (8, 3)``, ``Rk (3, 3)``,
    ``tk (3,)``: Kabsch work space. Updates
    ``bodies.err``, ``kerr`` (module docstring, step 3), ``R``, ``t``, ``moving``,
    ``motion_dt`` (step 1) and ``mpos`` (this frame's observed member positions).
    """
    members, size, mpos, pred = bodies.members, bodies.size, bodies.mpos, bodies.pred
    err, kerr, moving = bodies.err, bodies.kerr, bodies.moving
    R, t, motion_dt = bodies.R, bodies.t, bodies.motion_dt
    alpha = 1.0 / memory if memory > 1.0 else 1.0
    for b in range(members.shape[0]):
        n = size[b]
        # step 3: errors of this frame's predictions (body and Kalman, each member)
        for k in range(n):
            m = members[b, k]
            if obs[m, 0] != obs[m, 0] or pred[b, k, 0] != pred[b, k, 0]:  # noqa: PLR0124
                continue
            e_b = 0.0
            e_k = 0.0
            for a in range(3):
                d = obs[m, a] - pred[b, k, a]
                e_b += d * d
                d = obs[m, a] - kx[m, a]
                e_k += d * d
            err[b, k] = _remember(err[b, k], e_b / 3.0, alpha)
            kerr[b, k] = _remember(kerr[b, k], e_k / 3.0, alpha)
        # step 1: the rigid motion from the previous frame's observed members to this frame's
        c = 0
        for k in range(n):
            m = members[b, k]
            if obs[m, 0] == obs[m, 0] and mpos[b, k, 0] == mpos[b, k, 0]:  # noqa: PLR0124
                for a in range(3):
                    src[c, a] = mpos[b, k, a]
                    dst[c, a] = obs[m, a]
                c += 1
        if c >= 3:
            _kabsch(src, dst, c, Rk, tk)
            if tau > 0.0 and _max_residual(src, dst, c, Rk, tk) > tau:
                c = 0  # no rigid motion explains the members: predict nothing
        moving[b] = c >= 3
        if c >= 3:
            for a in range(3):
                t[b, a] = tk[a]
                for e in range(3):
                    R[b, a, e] = Rk[a, e]
            motion_dt[b] = dt
        else:
            for k in range(n):  # a body that lost its motion starts its record again
                err[b, k] = np.nan
                kerr[b, k] = np.nan
        for k in range(n):
            m = members[b, k]
            for a in range(3):
                mpos[b, k, a] = obs[m, a]


@njit
def _remember(old, new, alpha):
    """Exponential memory that rises at once: ``max(new, (1 - alpha) old + alpha new)``; a NaN
    ``old`` (no record) starts at ``new``."""
    if old != old:  # noqa: PLR0124 (NaN test)
        return new
    v = (1.0 - alpha) * old + alpha * new
    return new if new > v else v
