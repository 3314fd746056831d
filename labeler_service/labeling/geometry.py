"""Rigid fits for callers outside the labeler (``offline``, training): validate once, then the
kernel.

The online labeler's rigid-body kernels (:mod:`labeler_service.labeling.kernels.rigid`: Horn's
closed-form absolute orientation, Horn 1987: Newton's root of its characteristic polynomial
and the adjugate, cyclic Jacobi rotations where that is ill-conditioned, no LAPACK call) take
raw arrays and trust them. The public functions here check shapes, dtypes and
finiteness once, raise a :class:`ValueError` naming the offending argument, and call them:

- :func:`kabsch`: the rotation and translation that best map one point set onto another;
- :func:`aligned_mean`: the mean shape of several frames of one point set, each moved onto a
  reference by its fit (a body's reference shape in training);
- :func:`horn_quaternions`: Horn's unit quaternion of many small point sets at once (the
  per-triangle rotations of the shoulder pipeline of Hong, Park and Hodgins 2009);
- :func:`rotation_angle`: the angle of rotation matrices (the shoulder's joints, the boot's
  half-turned segments).

Plain-numpy twins: ``tests/reference.py`` (``kabsch``) and ``tests/shoulder/reference.py``
(``horn_reference``).
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit
from labeler_service.labeling.kernels.rigid import COV0, _aligned_mean, _cov_add, _horn_quaternion
from labeler_service.labeling.kernels.rigid import _kabsch as _kabsch_kernel

__all__ = ["aligned_mean", "horn_quaternions", "kabsch", "rotation_angle"]


def _points(name: str, x: np.ndarray, *, ndim: int, finite: bool = True) -> np.ndarray:
    """``x`` as C-contiguous float64 with ``ndim`` dimensions and a last axis of 3."""
    a = np.ascontiguousarray(x, dtype=np.float64)
    if a.ndim != ndim or a.shape[-1] != 3:
        raise ValueError(f"{name} must be {ndim}-D with a last axis of 3, got shape {a.shape}")
    if finite and not np.isfinite(a).all():
        raise ValueError(f"{name} contains NaN or inf")
    return a


def kabsch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R (3, 3), t (3,))`` minimising ``sum_i |R src_i + t - dst_i|^2`` over proper rotations.

    ``src`` and ``dst`` are ``(n, 3)`` with ``n >= 3``, finite, row ``i`` of one matching row
    ``i`` of the other.
    """
    s = _points("src", src, ndim=2)
    d = _points("dst", dst, ndim=2)
    if s.shape != d.shape:
        raise ValueError(f"src {s.shape} and dst {d.shape} must have the same shape")
    if s.shape[0] < 3:
        raise ValueError(f"a rigid fit needs at least 3 points, got {s.shape[0]}")
    R = np.empty((3, 3))
    t = np.empty(3)
    _kabsch_kernel(s, d, s.shape[0], R, t)
    return R, t


def aligned_mean(frames: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Mean ``(n, 3)`` of ``frames (F, n, 3)`` after moving each onto ``ref (n, 3)`` by its
    :func:`kabsch` fit (all finite, ``F >= 1``; with ``n < 3`` the fit's rotation is one of
    many, as in the labeler's recovery)."""
    f = _points("frames", frames, ndim=3)
    r = _points("ref", ref, ndim=2)
    if f.shape[1:] != r.shape:
        raise ValueError(f"frames {f.shape} must be (F, {r.shape[0]}, 3) to match ref {r.shape}")
    if f.shape[0] < 1 or r.shape[0] < 1:
        raise ValueError(f"frames {f.shape} holds no frame or no point")
    out = np.empty(r.shape)
    _aligned_mean(f, r, out)
    return out


@njit
def _horn_batch(ref: np.ndarray, cur: np.ndarray, out: np.ndarray) -> None:
    """``ref`` (T,k,3) centred rest sets, ``cur`` (F,T,k,3) -> ``out`` (F,T,4) (w,x,y,z)."""
    n_frames, n_sets, k = cur.shape[0], cur.shape[1], cur.shape[2]
    for f in range(n_frames):
        for i in range(n_sets):
            # centre the current set; NaN anywhere -> NaN quaternion
            cx = cy = cz = 0.0
            for j in range(k):
                cx += cur[f, i, j, 0]
                cy += cur[f, i, j, 1]
                cz += cur[f, i, j, 2]
            cx /= k
            cy /= k
            cz /= k
            if np.isnan(cx) or np.isnan(cy) or np.isnan(cz):
                for c in range(4):
                    out[f, i, c] = np.nan
                continue
            cov = COV0
            for j in range(k):
                cov = _cov_add(
                    cov,
                    ref[i, j, 0],
                    ref[i, j, 1],
                    ref[i, j, 2],
                    cur[f, i, j, 0] - cx,
                    cur[f, i, j, 1] - cy,
                    cur[f, i, j, 2] - cz,
                )
            q0, q1, q2, q3 = _horn_quaternion(cov)
            sign = 1.0 if q0 >= 0.0 else -1.0
            out[f, i, 0] = sign * q0
            out[f, i, 1] = sign * q1
            out[f, i, 2] = sign * q2
            out[f, i, 3] = sign * q3


def horn_quaternions(ref: np.ndarray, cur: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(F, T, 4)`` (w, x, y, z; w >= 0) rotating each rest point set onto its
    current pose by Horn's method; NaN where a point is missing.

    ``ref`` is ``(T, k, 3)`` [set, point, xyz] rest positions (finite, ``k >= 3``), ``cur``
    ``(F, T, k, 3)`` (NaN allowed).
    """
    r = _points("ref", ref, ndim=3)
    c = _points("cur", cur, ndim=4, finite=False)
    if r.shape[1] < 3:
        raise ValueError(f"ref must be (sets, k >= 3, 3), got {r.shape}")
    if c.shape[1:] != r.shape:
        raise ValueError(f"cur must be (frames, {r.shape[0]}, {r.shape[1]}, 3), got {c.shape}")
    ref_c = np.ascontiguousarray(r - r.mean(axis=1, keepdims=True))
    out = np.empty((c.shape[0], c.shape[1], 4))
    _horn_batch(ref_c, c, out)
    return out


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Rotation angle (radians) of rotation matrices (..., 3, 3)."""
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(c, -1.0, 1.0))
