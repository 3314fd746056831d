"""Batched rigid fits with missing samples (used by steps 3-5).

``fit_rigid`` is the least-squares rigid transform (Kabsch / Horn, SVD form) mapping rest-pose
points onto each frame's points; ``fit_rotation_about`` the rotation about a known pivot (a
ball joint: the child bone's rotation once its joint centre is placed by the parent). NaN
samples get zero weight; a frame with too few visible points gets a NaN transform, which
:func:`fill_transforms` replaces by the nearest valid frame's.
"""

from __future__ import annotations

import numpy as np


def _rotation_from_cov(H: np.ndarray) -> np.ndarray:
    """``R`` maximising ``trace(R H)`` for cross-covariances ``H`` (F, 3, 3) (proper, det +1)."""
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.transpose(0, 2, 1) @ U.transpose(0, 2, 1)))
    d[d == 0] = 1.0
    D = np.zeros_like(H)
    D[:, 0, 0] = 1.0
    D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    return Vt.transpose(0, 2, 1) @ D @ U.transpose(0, 2, 1)


def fit_rigid(
    src: np.ndarray, dst: np.ndarray, min_points: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """Rigid ``(R (F,3,3), t (F,3))`` with ``dst[f] ~ R[f] @ src + t[f]`` in least squares.

    ``src`` (M, 3) rest positions, ``dst`` (F, M, 3) with NaN for missing samples. Frames with
    fewer than ``min_points`` visible points get NaN.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    vis = ~np.isnan(dst).any(axis=2)
    W = vis.astype(np.float64)  # (F, M): a missing sample has zero weight
    wsum = W.sum(axis=1)
    ok = (vis.sum(axis=1) >= min_points) & (wsum > 0)
    safe = np.where(ok, wsum, 1.0)
    d0 = np.where(vis[..., None], dst, 0.0)
    cs = (W @ src) / safe[:, None]
    cd = np.matmul(W[:, None, :], d0)[:, 0] / safe[:, None]
    a = src[None] - cs[:, None]
    b = d0 - cd[:, None]
    H = np.matmul((W[:, :, None] * a).transpose(0, 2, 1), b)
    R = _rotation_from_cov(H)
    t = cd - np.einsum("fij,fj->fi", R, cs)
    R[~ok] = np.nan
    t[~ok] = np.nan
    return R, t


def fit_rotation_about(
    pivot_rest: np.ndarray, pivot_world: np.ndarray, src: np.ndarray, dst: np.ndarray,
    min_points: int = 2,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Rotation about a joint: ``dst[f] - J[f] ~ R[f] (src - j)``; returns ``(R, t)`` with
    ``t = J - R j`` so that ``R @ x + t`` maps rest space to the frame (NaN where undetermined).
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    vis = ~np.isnan(dst).any(axis=2)
    ok = (vis.sum(axis=1) >= min_points) & np.isfinite(pivot_world).all(axis=1)
    a = src - pivot_rest[None]
    b = np.where(vis[..., None], dst - pivot_world[:, None], 0.0)
    H = np.matmul(a.T[None], b)  # missing samples are zero in b
    R = _rotation_from_cov(np.nan_to_num(H))
    t = pivot_world - np.einsum("fij,j->fi", R, pivot_rest)
    R[~ok] = np.nan
    t[~ok] = np.nan
    return R, t


def fill_transforms(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Replaces NaN frames of ``(R, t)`` by the nearest valid frame (identity if none)."""
    ok = np.isfinite(R).all(axis=(1, 2)) & np.isfinite(t).all(axis=1)
    if ok.all():
        return R, t
    if not ok.any():
        n = R.shape[0]
        return np.repeat(np.eye(3)[None], n, axis=0), np.zeros((n, 3))
    idx = np.flatnonzero(ok)
    frames = np.arange(R.shape[0])
    pos = np.clip(np.searchsorted(idx, frames), 1, max(1, idx.size - 1))
    if idx.size == 1:
        nearest = np.zeros_like(frames) + idx[0]
    else:
        left, right = idx[pos - 1], idx[np.minimum(pos, idx.size - 1)]
        nearest = np.where(np.abs(frames - left) <= np.abs(right - frames), left, right)
    return R[nearest], t[nearest]


def apply(R: np.ndarray, t: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``R @ p + t`` for transforms (F, 3, 3), (F, 3) and rest points (M, 3) -> (F, M, 3)."""
    return np.matmul(R, points.T).transpose(0, 2, 1) + t[:, None, :]


def apply_point(R: np.ndarray, t: np.ndarray, point: np.ndarray) -> np.ndarray:
    """``R @ p + t`` for transforms (F, 3, 3), (F, 3) and one rest point (3,) -> (F, 3)."""
    return np.einsum("fij,j->fi", R, point) + t
