"""Step 2a: per-triangle rotations and their log map (Hong et al. 2009, Sec. 3.2).

For triangle ``i`` at frame ``t`` the rotational displacement from the rest pose is the unit
quaternion ``q_i^t`` of Horn's closed-form absolute orientation [Hor87]: with the centred rest
vertices ``a_j`` and current vertices ``b_j``, ``S = sum_j a_j b_j^T`` and the symmetric 4x4
matrix ``N(S)`` of Horn's Eq. (Sec. 4 of [Hor87]), ``q`` is the eigenvector of the largest
eigenvalue of ``N``. The feature of the triangle is ``F_i = [v_i^1 ... v_i^T]`` with
``v = log(q)`` the logarithm map of Lee and Shin [LS02]: ``q = (cos|v|, sin|v| v/|v|)``, i.e.
``v`` is the rotation axis times *half* the rotation angle, taken on the hemisphere ``w >= 0``.

The eigenvector comes from the labeler's own Horn solver through its public, validating entry
:func:`labeler_service.labeling.geometry.horn_quaternions` (Newton's root of ``N``'s
characteristic polynomial and its adjugate, cyclic Jacobi rotations where that is
ill-conditioned, no LAPACK call; the one the online labeler's Kabsch fits use). Its plain-numpy twin
(``numpy.linalg.eigh``) is in tests/shoulder/reference.py.
"""

from __future__ import annotations

import numpy as np

from labeler_service.labeling.geometry import horn_quaternions

__all__ = [
    "continuous_sign",
    "exp_map",
    "fill_gaps",
    "horn_quaternions",
    "log_map",
    "triangle_features",
]


def continuous_sign(q: np.ndarray, start: int = 0, max_step_deg: float = 60.0) -> np.ndarray:
    """Signs of quaternions ``(F, T, 4)`` made continuous in time; impossible jumps set to NaN.

    ``q`` and ``-q`` are the same rotation and Horn's method returns either. Walking away from
    frame ``start`` (the rest pose, where every ``q`` is the identity), each quaternion takes the
    sign closest to the last trusted one of its triangle. A quaternion more than
    ``max_step_deg`` (times the frames elapsed) away from the last trusted one is physically
    impossible for a skin triangle at capture rates -- it is a flat triangle's ill-conditioned
    estimate -- so it becomes NaN (later filled by interpolation) and cannot flip the sign of
    the rest of the sequence. Without this a rotation passing 180 degrees jumps across the log
    map's cut and one rigid segment's triangles scatter (our addition; the paper is silent).
    """
    q = np.array(q, dtype=np.float64, copy=True)
    n, t = q.shape[0], q.shape[1]
    half_step = np.deg2rad(max_step_deg) / 2.0
    for order in (range(start, n), range(start, -1, -1)):
        last = np.zeros((t, 4))
        last[:, 0] = 1.0
        age = np.zeros(t)
        for f in order:
            cur = q[f]
            dot = np.einsum("ti,ti->t", cur, last)
            ok = np.isfinite(dot)
            flip = ok & (dot < 0)
            cur[flip] *= -1.0
            age += 1.0
            limit = np.cos(np.minimum(half_step * age, np.pi / 2))
            jump = ok & (np.abs(dot) < limit)
            if f != start:
                cur[jump] = np.nan
            good = ok & ~jump
            last[good] = cur[good]
            age[good] = 0.0
    return q


def log_map(q: np.ndarray) -> np.ndarray:
    """Logarithm map of unit quaternions ``(..., 4)`` (w, x, y, z) -> ``(..., 3)`` [LS02].

    ``log(q) = atan2(|u|, w) u / |u|`` with ``u = (x, y, z)``, so ``|v|`` is half the rotation
    angle; on the hemisphere ``w >= 0`` ``|v| <= pi / 2``, and up to ``pi`` for ``w < 0`` (sign
    chosen by :func:`continuous_sign`); NaN stays NaN.
    """
    q = np.asarray(q, dtype=np.float64)
    u = q[..., 1:]
    nu = np.linalg.norm(u, axis=-1, keepdims=True)
    theta = np.arctan2(nu, q[..., :1])
    with np.errstate(invalid="ignore", divide="ignore"):
        factor = np.where(nu > 1e-12, theta / np.where(nu > 1e-12, nu, 1.0), 1.0)
    return u * factor


def exp_map(v: np.ndarray) -> np.ndarray:
    """Inverse of :func:`log_map`: ``(..., 3)`` -> unit quaternions ``(..., 4)``."""
    v = np.asarray(v, dtype=np.float64)
    nv = np.linalg.norm(v, axis=-1, keepdims=True)
    sinc = np.where(nv > 1e-12, np.sin(nv) / np.where(nv > 1e-12, nv, 1.0), 1.0)
    return np.concatenate([np.cos(nv), v * sinc], axis=-1)


def fill_gaps(x: np.ndarray) -> np.ndarray:
    """Linear interpolation in time of NaN rows of ``x`` (F, D) per column; ends held constant.

    A column with no finite value becomes 0 (identity rotation in log space).
    """
    x = np.array(x, dtype=np.float64, copy=True)
    t = np.arange(x.shape[0])
    bad = np.isnan(x)
    for c in np.flatnonzero(bad.any(axis=0)):
        good = ~bad[:, c]
        x[:, c] = np.interp(t, t[good], x[good, c]) if good.any() else 0.0
    return x


def triangle_features(
    positions: np.ndarray, rest: np.ndarray, faces: np.ndarray, rest_frame: int = 0
) -> np.ndarray:
    """Clustering features ``(T, 3F)``: row ``i`` is ``F_i = [v_i^1 ... v_i^F]`` (Sec. 3.2).

    ``positions`` (F, M, 3) mm (NaN = missing), ``rest`` (M, 3) (the pose of frame
    ``rest_frame``), ``faces`` (T, 3). Quaternion signs follow :func:`continuous_sign`. Frames
    where a triangle has a missing vertex (or an impossible jump) get its log-map vector
    interpolated in time (:func:`fill_gaps`).
    """
    pos = np.asarray(positions, dtype=np.float64)
    q = horn_quaternions(rest[faces], pos[:, faces])  # (F, T, 4)
    v = log_map(continuous_sign(q, rest_frame))  # (F, T, 3)
    f, t = v.shape[:2]
    v = fill_gaps(v.reshape(f, t * 3)).reshape(f, t, 3)
    return np.ascontiguousarray(v.transpose(1, 0, 2).reshape(t, f * 3))
