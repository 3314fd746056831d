"""Step 5b: joint angles from markers, skinning synthesis, errors (Hong et al. 2009, Sec. 4).

Pose (joint angles) from a marker set, top-down along the chain: the root bone is a rigid fit
of its markers; each next bone is the rotation about its joint centre (placed by the already
posed parent) that best maps its markers (:func:`~offline.shoulder.rigid.fit_rotation_about`).
Frames where a bone has too few visible markers take the nearest valid frame's pose.

Synthesis: single-weight enveloping (linear blend skinning) of the rest-pose marker surface,
``p_m^t = sum_s w_ms T_s^t p_hat_m``; the error is ``||p_m^t - captured||`` over every visible
sample (Table 2: avg, max, std in mm).

MG03 baseline (Table 3): the 3-segment skeleton plus an extra bone at the shoulder (the root's
first joint) that takes half of the shoulder rotation (``R_half = exp(log(R_rel) / 2)`` about the
same centre); skin weights over the four bones solved from the training motion by non-negative
least squares with a sum-to-one row (Mohr and Gleicher fit weights to examples), on every 4th
frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import nnls
from scipy.spatial.transform import Rotation

from offline.shoulder.rigid import (
    apply,
    apply_point,
    fill_transforms,
    fit_rigid,
    fit_rotation_about,
)


@dataclass(frozen=True)
class ErrorStats:
    """Synthesis error over visible samples (mm)."""

    avg: float
    max: float
    std: float
    samples: int

    def as_dict(self) -> dict:
        return {"avg": self.avg, "max": self.max, "std": self.std, "samples": self.samples}


def pose_chain(
    positions: np.ndarray,
    rest: np.ndarray,
    order: Sequence[int],
    parent: np.ndarray,
    joints: dict[int, np.ndarray],
    fit_markers: Sequence[np.ndarray],
) -> tuple[np.ndarray, np.ndarray]:
    """Bone transforms ``R (F, S, 3, 3)``, ``t (F, S, 3)`` from markers (module doc).

    ``order`` lists the bones parents first (root first), ``parent[c]`` is ``c``'s parent;
    ``joints[c]`` the rest-space centre of the joint between ``c`` and its parent;
    ``fit_markers[s]`` the marker indices used for bone ``s``.
    """
    n = positions.shape[0]
    S = len(fit_markers)
    R = np.empty((n, S, 3, 3))
    t = np.empty((n, S, 3))
    root = order[0]
    idx = fit_markers[root]
    Rr, tr = fit_rigid(rest[idx], positions[:, idx])
    R[:, root], t[:, root] = fill_transforms(Rr, tr)
    for child in order[1:]:
        p = int(parent[child])
        j = joints[child]
        J = apply_point(R[:, p], t[:, p], j)
        idx = fit_markers[child]
        Rc, tc = fit_rotation_about(j, J, rest[idx], positions[:, idx])
        Rc, tc = fill_transforms(Rc, tc)
        R[:, child], t[:, child] = Rc, tc
    return R, t


def skin(rest: np.ndarray, weights: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Linear blend skinning: ``(F, M, 3)`` from weights ``(M, S)`` and bone transforms."""
    out = np.zeros((R.shape[0], rest.shape[0], 3))
    for s in range(R.shape[1]):
        w = weights[:, s]
        if not (w > 0).any():
            continue
        out += w[None, :, None] * apply(R[:, s], t[:, s], rest)
    return out


def error_stats(synth: np.ndarray, captured: np.ndarray) -> ErrorStats:
    """Per-sample Euclidean error over samples visible in ``captured`` and finite in ``synth``."""
    d = np.linalg.norm(synth - captured, axis=2)
    d = d[np.isfinite(d)]
    if d.size == 0:
        return ErrorStats(float("nan"), float("nan"), float("nan"), 0)
    return ErrorStats(float(d.mean()), float(d.max()), float(d.std()), int(d.size))


# ------------------------------------------------------------------------------ MG03
def half_rotation(R_parent: np.ndarray, R_child: np.ndarray) -> np.ndarray:
    """``R_parent @ exp(log(R_parent^T R_child) / 2)`` per frame (the halfway bone's rotation)."""
    rel = np.einsum("fji,fjk->fik", R_parent, R_child)
    rv = Rotation.from_matrix(rel).as_rotvec()
    return R_parent @ Rotation.from_rotvec(0.5 * rv).as_matrix()


def mg03_bones(
    R: np.ndarray, t: np.ndarray, order: Sequence[int], shoulder: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Adds the MG03 halfway bone (index ``S``) at the root's first joint (the shoulder)."""
    root, first = order[0], order[1]
    Rh = half_rotation(R[:, root], R[:, first])
    J = apply_point(R[:, root], t[:, root], shoulder)
    th = J - np.einsum("fij,j->fi", Rh, shoulder)
    return (np.concatenate([R, Rh[:, None]], axis=1), np.concatenate([t, th[:, None]], axis=1))


def fit_weights_nnls(
    positions: np.ndarray, rest: np.ndarray, R: np.ndarray, t: np.ndarray, step: int = 4
) -> np.ndarray:
    """Per-marker skin weights ``(M, B)`` by NNLS on the training frames, rows summing to 1."""
    pos = positions[::step]
    Rs, ts = R[::step], t[::step]
    per_bone = np.einsum("fsij,mj->fsmi", Rs, rest) + ts[:, :, None, :]  # (F, B, M, 3)
    n_b = R.shape[1]
    W = np.zeros((rest.shape[0], n_b))
    for m in range(rest.shape[0]):
        vis = np.isfinite(pos[:, m]).all(axis=1) & np.isfinite(per_bone[:, :, m]).all(axis=(1, 2))
        if vis.sum() < 2:
            W[m, 0] = 1.0
            continue
        A = per_bone[vis, :, m].transpose(0, 2, 1).reshape(-1, n_b)  # (F*3, B)
        b = pos[vis, m].reshape(-1)
        scale = 1e3 * np.sqrt(vis.sum())
        A = np.vstack([A, np.full((1, n_b), scale)])
        b = np.append(b, scale)
        w, _ = nnls(A, b)
        W[m] = w / w.sum() if w.sum() > 0 else np.eye(n_b)[0]
    return W
