"""Step 5a: markers to segments, and skin weights (Hong et al. 2009, Sec. 3.5, after [PH06]).

* Hard label: each marker takes the cluster of most of its (near-rigid) triangles. A marker on
  no clustered triangle takes the segment whose rigid motion predicts it best.
* Segment motion: a rigid fit (:func:`~offline.shoulder.rigid.fit_rigid`) of the segment's
  markers, rest pose -> each frame.
* Rigid core: the segment's markers whose own rigid residual is at most 2.5x the segment median
  (skin near a joint that turns only part of the way is left out of the bone's motion).
* Weights: a marker *inside* a segment (no other label within two mesh rings) has weight 1
  for it. A *boundary* marker gets weights over the segments within two rings from the
  likelihood that it belongs to each, computed from the distance between the captured marker and
  the marker moved rigidly by each segment. The paper does not give the function; we use
  ``e_s = mean_t ||p^t - T_s^t p_hat||^2`` (mean squared distance), its noise-free part
  ``d_s = sqrt(max(e_s - sigma^2, 0.01 sigma^2))`` (``sigma^2``: median ``e`` of the core
  markers under their own segment, the rigid-fit noise level of this capture), ``L_s = 1 / d_s``
  for segments with ``d_s <= 4 min d``, 0 otherwise, and ``w_s = L_s / sum L``. For a marker
  that truly moves as the linear blend ``w p_A + (1 - w) p_B`` of two bones, ``d_A = (1-w) D``
  and ``d_B = w D``, so these weights recover ``w`` exactly; a marker that moves rigidly with
  one segment gets weight ~1 there. (A Gaussian ``exp(-e / 2 sigma^2)`` is all but binary once
  the segments' predictions differ by more than the noise.)
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from offline.shoulder.rigid import apply, fit_rigid


def vote_labels(faces: np.ndarray, tri_labels: np.ndarray, n_markers: int, k: int) -> np.ndarray:
    """Marker votes ``(M, k)``: how many clustered triangles of each cluster use the marker."""
    votes = np.zeros((n_markers, k), dtype=np.int64)
    for c in range(3):
        np.add.at(votes, (faces[:, c], tri_labels), 1)
    return votes


def segment_fits(
    positions: np.ndarray, rest: np.ndarray, members: Sequence[np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Rigid motion of every segment: ``R (F, S, 3, 3)``, ``t (F, S, 3)`` (NaN if undetermined)."""
    Rs, ts = [], []
    for idx in members:
        R, t = fit_rigid(rest[idx], positions[:, idx])
        Rs.append(R)
        ts.append(t)
    return np.stack(Rs, axis=1), np.stack(ts, axis=1)


def rigid_residuals(
    positions: np.ndarray, rest: np.ndarray, R: np.ndarray, t: np.ndarray
) -> np.ndarray:
    """``e[m, s] = mean_t ||p_m^t - T_s^t p_hat_m||^2`` over frames where both exist (mm^2)."""
    S = R.shape[1]
    out = np.empty((rest.shape[0], S))
    for s in range(S):
        pred = apply(R[:, s], t[:, s], rest)
        d2 = ((positions - pred) ** 2).sum(axis=2)
        out[:, s] = np.nanmean(np.where(np.isfinite(d2), d2, np.nan), axis=0)
    return np.where(np.isfinite(out), out, np.inf)


def hard_labels(
    positions: np.ndarray,
    rest: np.ndarray,
    faces: np.ndarray,
    tri_labels: np.ndarray,
    k: int,
) -> np.ndarray:
    """Segment of every marker (module doc); ``-1`` never remains."""
    m = rest.shape[0]
    votes = vote_labels(faces, tri_labels, m, k)
    labels = np.where(votes.sum(axis=1) > 0, np.argmax(votes, axis=1), -1)
    if (labels < 0).any():
        # a cluster that won fewer than 3 markers moves with the markers of its triangles (a
        # marker labelled s is on one of them: its votes for s are its largest, so > 0)
        R, t = segment_fits(positions, rest, segment_members(labels, k, faces, tri_labels))
        e = rigid_residuals(positions, rest, R, t)
        free = labels < 0
        labels[free] = np.argmin(e[free], axis=1)
    return labels.astype(np.intp)


def merge_small_segments(
    positions: np.ndarray, rest: np.ndarray, labels: np.ndarray, k: int, min_markers: int
) -> tuple[np.ndarray, int]:
    """Relabels the markers of segments owning fewer than ``min_markers`` markers to the
    remaining segment whose rigid motion predicts each best (smallest first). Returns the new
    labels (numbering unchanged, merged segments empty) and how many segments were merged."""
    labels = labels.copy()
    merged = 0
    while True:
        counts = np.bincount(labels, minlength=k)
        alive = np.flatnonzero(counts > 0)
        small = [s for s in alive if counts[s] < min_markers]
        if not small or alive.size <= 1:
            return labels, merged
        s = min(small, key=lambda x: (counts[x], x))
        others = [o for o in alive if o != s]
        members = [np.flatnonzero(labels == o) for o in others]
        R, t = segment_fits(positions, rest, members)
        idx = np.flatnonzero(labels == s)
        e = rigid_residuals(positions[:, idx], rest[idx], R, t)
        labels[idx] = np.asarray(others)[np.argmin(e, axis=1)]
        merged += 1


def segment_members(labels: np.ndarray, k: int, faces: np.ndarray, tri_labels: np.ndarray) -> list:
    """Marker indices defining each segment's rigid motion (its labelled markers, or the markers
    of its triangles when fewer than 3 carry its label)."""
    out = []
    for s in range(k):
        idx = np.flatnonzero(labels == s)
        if idx.size < 3:
            idx = np.unique(np.concatenate([idx, faces[tri_labels == s].ravel()]))
        out.append(idx)
    return out


def core_members(
    residuals: np.ndarray, members: Sequence[np.ndarray], factor: float = 2.5
) -> list[np.ndarray]:
    """The rigid core of each segment: its markers whose own rigid residual is at most
    ``factor`` times the segment's median (skin near a joint that turns only part of the way is
    left out, so it does not bias the bone's motion or its joint centre). At least 3 markers
    (the best ones) are kept."""
    out = []
    for s, idx in enumerate(members):
        e = residuals[idx, s]
        med = float(np.median(e[np.isfinite(e)])) if np.isfinite(e).any() else np.inf
        keep = idx[e <= factor * med]
        if keep.size < 3:
            keep = idx[np.argsort(e, kind="stable")[: min(3, idx.size)]]
        out.append(np.sort(keep))
    return out


def boundary_candidates(labels: np.ndarray, neighbors: Sequence[np.ndarray]) -> list[np.ndarray]:
    """Segments each marker may blend between: the labels within two mesh rings of it."""
    out = []
    for i, nb in enumerate(neighbors):
        ring2 = np.concatenate([nb, *(neighbors[j] for j in nb)]) if nb.size else nb
        out.append(np.unique(np.concatenate([labels[ring2], [labels[i]]])).astype(np.intp))
    return out


def skin_weights(
    labels: np.ndarray,
    residuals: np.ndarray,
    candidates: Sequence[np.ndarray],
    k: int,
    core: Sequence[np.ndarray],
) -> tuple[np.ndarray, float]:
    """Weights ``(M, k)`` (rows sum to 1) and the ``sigma^2`` used (module doc).

    ``sigma^2`` is the median own-segment residual of the ``core`` markers.
    """
    m = labels.shape[0]
    pool = np.concatenate([residuals[idx, s] for s, idx in enumerate(core)])
    pool = pool[np.isfinite(pool)]
    sigma2 = max(float(np.median(pool)) if pool.size else 1.0, 1e-6)
    W = np.zeros((m, k))
    for i, cand in enumerate(candidates):
        e = residuals[i, cand]
        if cand.size == 1 or not np.isfinite(e.min()):
            W[i, labels[i]] = 1.0
            continue
        d = np.sqrt(np.maximum(e - sigma2, 0.01 * sigma2))
        L = np.where(d <= 4.0 * d.min(), 1.0 / d, 0.0)
        W[i, cand] = L / L.sum()
    return W, sigma2
